"""Posed image datasets: cameras, conventions, images and the readers/writers of each format.

Modules:
    cameras  -- :class:`Camera`, OpenCV/OpenGL/Mitsuba conventions, rays
    images   -- reading/writing images as float RGB
    storage  -- how a split keeps its images in memory (compactly)
    dataset  -- :class:`Dataset` / :class:`Split`, shared validation, normalization applied
    nerfpp   -- the NeRF++ layout (read and write)
    blender  -- ``transforms.json`` (Blender / NeRF synthetic, instant-ngp, nerfstudio)
    llff     -- ``poses_bounds.npy``
    colmap   -- COLMAP sparse models (``sparse/0/`` + ``images/``)
    formats  -- :func:`load_dataset`, which detects the format
"""
from mi_nerfpp.data.blender import read_transforms
from mi_nerfpp.data.cameras import (Camera, direction_coverage,
                                    mitsuba_sensor_dict, mitsuba_to_opencv,
                                    opencv_to_mitsuba, opencv_to_opengl,
                                    opengl_to_opencv, pixel_rays, project)
from mi_nerfpp.data.colmap import read_colmap
from mi_nerfpp.data.dataset import AutoDownscale, Dataset, Split
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.formats import detect_format, load_dataset
from mi_nerfpp.data.images import (downscale_image, image_size, read_image,
                                   write_encoded_png)
from mi_nerfpp.data.llff import llff_to_opencv, read_llff
from mi_nerfpp.data.nerfpp import read_nerfpp, write_nerfpp

__all__ = [
    'AutoDownscale', 'Camera', 'Dataset', 'DatasetError', 'Split', 'detect_format',
    'direction_coverage',
    'downscale_image', 'image_size', 'read_colmap',
    'llff_to_opencv', 'load_dataset', 'mitsuba_sensor_dict', 'mitsuba_to_opencv',
    'opencv_to_mitsuba', 'opencv_to_opengl', 'opengl_to_opencv',
    'pixel_rays', 'project', 'read_image', 'read_llff', 'read_nerfpp', 'read_transforms',
    'write_encoded_png', 'write_nerfpp',
]

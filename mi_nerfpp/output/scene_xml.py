"""Writing ready-to-render Mitsuba scene files for a trained model."""
from __future__ import annotations

import os

from mi_nerfpp.data import Camera, opencv_to_mitsuba
from mi_nerfpp.files.atomic import atomic_write_path

TEMPLATE = """<scene version="3.0.0">
    <!-- Written by mi-nerfpp: render with
         python -m mi_nerfpp render {name} -o render.exr --preview render.png -->
    <integrator type="nerfpp">
        <string name="checkpoint" value="{checkpoint}"/>
        <!-- Sample counts and background: the checkpoint's (those it was trained with).
             Override them here, e.g. <integer name="fine_samples" value="32"/>. -->
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="{fov:.9g}"/>
        <string name="fov_axis" value="x"/>
        <float name="principal_point_offset_x" value="{ppx:.9g}"/>
        <float name="principal_point_offset_y" value="{ppy:.9g}"/>
        <float name="near_clip" value="{near:.9g}"/>
        <transform name="to_world">
            <matrix value="{matrix}"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="1"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{w}"/>
            <integer name="height" value="{h}"/>
            <rfilter type="box"/>
            <string name="pixel_format" value="rgba"/>
        </film>
    </sensor>
</scene>
"""


def write_render_xml(path, checkpoint, camera: Camera, near_clip):
    """Write a scene rendering ``checkpoint`` from ``camera`` (world frame, OpenCV pose).

    ``checkpoint`` is stored relative to the XML file's folder when it lies below it; the
    integrator resolves relative paths against the scene file's folder. The integrator takes
    the sample counts and the background from the checkpoint.
    """
    folder = os.path.dirname(os.path.abspath(path))
    ckpt = os.path.abspath(checkpoint)
    if os.path.commonpath([folder, ckpt]) == folder:
        ckpt = os.path.relpath(ckpt, folder)
    K = camera.K
    matrix = ' '.join(f'{v:.9g}' for v in opencv_to_mitsuba(camera.c2w).ravel())
    text = TEMPLATE.format(name=os.path.basename(path), checkpoint=ckpt, fov=camera.fov_x,
                           ppx=0.5 - K[0, 2] / camera.width, ppy=0.5 - K[1, 2] / camera.height,
                           near=near_clip, matrix=matrix, w=camera.width, h=camera.height)
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        f.write(text)

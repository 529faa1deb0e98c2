"""The textured proxy of an export in Blender's viewport, rendered headless (Workbench, flat
lighting, texture colour) from one of the exported cameras, beside that camera's photo:
docs/images/textured_proxy_blender.png.

    .venv-bpy/bin/python scripts/proxy_screenshot.py DIR DATASET [--camera test:000000]
        [--out docs/images/textured_proxy_blender.png]

``DIR``: the folder ``python -m mi_nerfpp export`` wrote (proxy.obj, cameras.json); ``DATASET``:
the run's dataset in the NeRF++ layout (``<split>/rgb/<name>.png``). Blender 4.2 as a module
(``bpy``, in .venv-bpy: ``scripts/setup.sh --test``), which reads and writes the PNGs.
"""
import argparse
import json
import os
import tempfile

import bpy
import numpy as np
from mathutils import Matrix

WIDTH = 640


def render(obj, camera, path):
    """``obj`` (world axes as in the file) seen from ``camera`` (a cameras.json entry)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.obj_import(filepath=obj, forward_axis='Y', up_axis='Z')    # the file's own axes
    scene = bpy.context.scene
    scene.render.resolution_x = WIDTH
    scene.render.resolution_y = round(WIDTH * camera['height'] / camera['width'])
    data = bpy.data.cameras.new('view')
    data.sensor_fit, data.sensor_width = 'HORIZONTAL', 36.0
    data.lens = camera['K'][0][0] * 36.0 / camera['width']
    data.clip_start, data.clip_end = 0.01, 1000.0
    view = bpy.data.objects.new('view', data)
    scene.collection.objects.link(view)
    view.matrix_world = Matrix(camera['c2w']) @ Matrix.Diagonal((1, -1, -1, 1))   # OpenCV
    scene.camera = view
    scene.render.engine = 'BLENDER_WORKBENCH'
    scene.display.shading.light, scene.display.shading.color_type = 'FLAT', 'TEXTURE'
    scene.view_settings.view_transform = 'Standard'
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def read(path):
    """The 8-bit image ``path`` as H x W x 4 floats in [0, 1], top row first."""
    image = bpy.data.images.load(path)
    w, h = image.size
    pixels = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(h, w, 4)[::-1]


def write(path, pixels):
    """H x W x 4 floats in [0, 1], top row first, as an 8-bit PNG."""
    h, w = pixels.shape[:2]
    image = bpy.data.images.new('out', w, h)
    image.pixels.foreach_set(np.ascontiguousarray(pixels[::-1], np.float32).ravel())
    image.filepath_raw, image.file_format = os.path.abspath(path), 'PNG'
    image.save()


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('export')
    p.add_argument('dataset')
    p.add_argument('--camera', default='test:000000', help='SPLIT:NAME of cameras.json')
    p.add_argument('--out', default='docs/images/textured_proxy_blender.png')
    args = p.parse_args()
    split, name = args.camera.split(':')
    cameras = json.load(open(os.path.join(args.export, 'cameras.json')))['cameras']
    camera = next(c for c in cameras if c['split'] == split and c['name'] == name)
    with tempfile.TemporaryDirectory() as tmp:
        render(os.path.join(args.export, 'proxy.obj'), camera, os.path.join(tmp, 'shot.png'))
        shot = read(os.path.join(tmp, 'shot.png'))
    photo = read(os.path.join(args.dataset, split, 'rgb', name + '.png'))
    scale = shot.shape[1] // photo.shape[1]
    photo = np.kron(photo, np.ones((scale, scale, 1), np.float32))[:shot.shape[0]]
    photo[..., 3] = shot[..., 3] = 1.0
    gap = np.ones((shot.shape[0], 8, 4), np.float32)
    write(args.out, np.concatenate([photo, gap, shot], axis=1))
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()

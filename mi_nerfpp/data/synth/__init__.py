"""Synthetic captures of Mitsuba scenes (``python -m mi_nerfpp synth``), in four modules:

- :mod:`.capture`: the capture renderer and its cache (:func:`synthesize`,
  :func:`default_capture`, the ground-truth layers, the scenes that come with mi-nerfpp);
- :mod:`.trajectories`: where the cameras are (``orbit``, ``truck``, ``hemisphere``, ``arc``);
- :mod:`.degrade`: degraded copies of a capture for tests and benchmarks
  (:func:`vary_exposure`, :func:`perturb_poses`);
- :mod:`.clip`: rendered frames as a video (:func:`encode_clip`).

Their public names are importable from here (``from mi_nerfpp.data.synth import synthesize``).
"""
from mi_nerfpp.data.synth.capture import (CAPTURE_FILE, CAPTURE_FORMAT,
                                          CAPTURE_VERSION, DEFAULT_RES,
                                          DEFAULT_SCENE, DEFAULT_SPP,
                                          DEFAULT_TRAJECTORY, DEFAULT_VIEWS,
                                          cache_dir, default_capture,
                                          render_ground_truth, scene_file,
                                          scenes_dir, synthesize)
from mi_nerfpp.data.synth.clip import CLIP_CRF, CLIP_FPS, encode_clip
from mi_nerfpp.data.synth.degrade import (APPEARANCE_FILE, POSES_FILE,
                                          perturb_poses, vary_exposure)
from mi_nerfpp.data.synth.trajectories import (ARC_AZIMUTH, ARC_AZIMUTH_JITTER,
                                               ARC_ELEVATION,
                                               ARC_EXTRAPOLATION, DEFAULT_FOV,
                                               DEFAULT_RADIUS, DEFAULT_SEED,
                                               HELD_OUT_FRACTION,
                                               HEMISPHERE_ELEVATION,
                                               ORBIT_AZIMUTH_JITTER,
                                               ORBIT_ELEVATION,
                                               ORBIT_RADIUS_JITTER,
                                               ORBIT_TARGET_JITTER,
                                               TRAJECTORIES, TRUCK_FILES,
                                               arc_cameras, hemisphere_cameras,
                                               intrinsics_from_fov, look_at,
                                               make_cameras, orbit_cameras,
                                               parse_res, split_counts,
                                               truck_alignment, truck_cameras)

__all__ = [
    'APPEARANCE_FILE', 'ARC_AZIMUTH', 'ARC_AZIMUTH_JITTER', 'ARC_ELEVATION', 'ARC_EXTRAPOLATION',
    'CAPTURE_FILE', 'CAPTURE_FORMAT', 'CAPTURE_VERSION', 'CLIP_CRF', 'CLIP_FPS', 'DEFAULT_FOV',
    'DEFAULT_RADIUS',
    'DEFAULT_RES', 'DEFAULT_SCENE', 'DEFAULT_SEED', 'DEFAULT_SPP', 'DEFAULT_TRAJECTORY',
    'DEFAULT_VIEWS', 'HELD_OUT_FRACTION', 'HEMISPHERE_ELEVATION', 'ORBIT_AZIMUTH_JITTER',
    'ORBIT_ELEVATION', 'ORBIT_RADIUS_JITTER', 'ORBIT_TARGET_JITTER', 'POSES_FILE',
    'TRAJECTORIES', 'TRUCK_FILES', 'arc_cameras', 'cache_dir', 'default_capture', 'encode_clip',
    'hemisphere_cameras', 'intrinsics_from_fov', 'look_at', 'make_cameras', 'orbit_cameras',
    'parse_res', 'perturb_poses', 'render_ground_truth', 'scene_file', 'scenes_dir',
    'split_counts', 'synthesize', 'truck_alignment', 'truck_cameras', 'vary_exposure',
]

"""Import a segmo BVH into Blender headless and compare its bones with segmo's joints.

    blender -b --python tools/blender_import.py -- MOTION.bvh JOINTS.npy [--names JSON]

JOINTS are in t2m order (segmo's); --names gives another order as a JSON list of joint names.

Runs inside Blender (its own Python, `bpy`): imports the file with Blender's own BVH
importer (native per-bone rotation orders, y up converted to Blender's z up), plays every
frame, and measures each bone's head against the joints (t, 22, 3) in metres, and half way
between the file's frames against the mean of the bone heads at those two frames (Blender
interpolates the Euler curves: a flip of the angles, or a joint turning far in one frame,
swings a limb off that line). A file at a whole multiple k of the joints' frame rate (segmo
writes 60 fps for 20 fps joints) is compared at every k-th frame, where the joints are.
The last printed line is a JSON object: bones, frames, scene fps, frames per joints frame,
mean / max error and the half-frame deviation (mm).
"""

import builtins
import json
import sys

import bpy
import numpy as np

# Debian's Blender 3.4 runs its BVH importer on Python 3.11, which no longer takes the
# 'rU' mode the importer opens files with (ValueError: invalid mode: 'rU'); read as 'r'.
_open = builtins.open
builtins.open = lambda file, mode="r", *a, **k: _open(file, mode.replace("U", ""), *a, **k)

# segmo.motion.T2M.joint_names: Blender's own Python cannot import segmo (a test checks it)
T2M_JOINTS = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
]
argv = sys.argv[sys.argv.index("--") + 1:]
bvh_path, joints_path = argv[0], argv[1]
joints = np.load(joints_path).astype(np.float64)  # (t, j, 3), y up
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_anim.bvh(filepath=bvh_path, rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y",
                        update_scene_fps=True, update_scene_duration=True)
armature = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
names = [b.name for b in armature.pose.bones]
scene = bpy.context.scene
# the file's frames (the importer extends the scene's range, never shortens it)
first, last = armature.animation_data.action.frame_range
start = int(round(first))
frames = int(round(last - first)) + 1
every = max(1, (frames - 1) // max(len(joints) - 1, 1))  # a one-frame motion: 1
if (len(joints) - 1) * every + 1 != frames:
    sys.exit(f"blender_import: {bvh_path} has {frames} frames, not a whole multiple of the "
             f"{len(joints)} frames of {joints_path}")
heads = []
for f in range(frames):
    scene.frame_set(start + f)
    heads.append([list(armature.matrix_world @ armature.pose.bones[n].head) for n in names])
heads = np.asarray(heads)  # (t, bones, 3), Blender z up
halves = []  # Blender's interpolation half way between frames (where angle flips would show)
for f in range(frames - 1):
    scene.frame_set(start + f, subframe=0.5)
    halves.append([list(armature.matrix_world @ armature.pose.bones[n].head) for n in names])
halves = np.asarray(halves)
# Blender's axes from the file's y up, -z forward: (x, y, z)_bvh -> (x, -z, y)_blender
expected = np.stack([joints[..., 0], -joints[..., 2], joints[..., 1]], -1)
# The joints' order, to find each bone's joint by name (Blender orders the bones as the file
# lists them, depth first, not as the joints are stored).
from_names = json.loads(argv[argv.index("--names") + 1]) if "--names" in argv else T2M_JOINTS
order = [from_names.index(n) for n in names]
error = np.linalg.norm(heads[::every] - expected[:, order], axis=-1) * 1000
middle = (heads[1:] + heads[:-1]) / 2
between = np.linalg.norm(halves - middle, axis=-1) * 1000 if len(halves) else np.zeros(1)
print(json.dumps({"bones": len(names), "frames": len(heads), "fps": scene.render.fps, "every": every,
                  "mean_mm": round(float(error.mean()), 3), "max_mm": round(float(error.max()), 3),
                  "half_frame_vs_mean_of_neighbours_max_mm": round(float(between.max()), 2)}))

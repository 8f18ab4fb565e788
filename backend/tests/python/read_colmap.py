"""Open a COLMAP text model with pycolmap and print, as JSON: every camera (model, size,
parameters), rig (sensor poses) and frame (its images), every image's name, camera and
cam_from_world pose, the pixels the exported cameras give for the queried camera-frame
directions, and the reprojection error of every point observation through the exported images
and cameras. Used by backend/tests/export_splat.rs.

Usage: python3 read_colmap.py MODEL_DIR QUERIES.json
QUERIES.json: {"<camera_id>": [[x, y, z], ...]} directions in that camera's frame.
Exit status 3 when pycolmap is not installed (the test then skips with a message)."""
import json
import sys

try:
    import numpy as np
    import pycolmap
except ImportError:
    print("pycolmap is not installed (make deps installs it)", file=sys.stderr)
    sys.exit(3)

model_dir, queries_path = sys.argv[1], sys.argv[2]
rec = pycolmap.Reconstruction()
rec.read_text(model_dir)
with open(queries_path) as f:
    queries = json.load(f)


def pose(rigid):
    x, y, z, w = (float(v) for v in rigid.rotation.quat)
    return {"q_wxyz": [w, x, y, z], "t": [float(v) for v in rigid.translation]}


cameras = {}
for cid, cam in rec.cameras.items():
    entry = {
        "model": cam.model.name,
        "width": int(cam.width),
        "height": int(cam.height),
        "params": [float(v) for v in cam.params],
    }
    dirs = queries.get(str(cid))
    if dirs:
        pix = cam.img_from_cam(np.asarray(dirs, dtype=np.float64))
        entry["projected"] = [[float(u), float(v)] for u, v in pix]
    cameras[str(cid)] = entry

images = {}
for iid, img in rec.images.items():
    images[img.name] = {
        "id": int(iid),
        "camera_id": int(img.camera_id),
        "frame_id": int(img.frame_id),
        "cam_from_world": pose(img.cam_from_world()),
        "observations": int(img.num_points3D),
    }

rigs = {}
for rid, rig in rec.rigs.items():
    sensors = {}
    for sensor_id, sensor_from_rig in rig.non_ref_sensors.items():
        sensors[str(sensor_id.id)] = pose(sensor_from_rig) if sensor_from_rig is not None else None
    rigs[str(rid)] = {"ref_camera": int(rig.ref_sensor_id.id), "sensors": sensors}

frames = {}
for fid, frame in rec.frames.items():
    frames[str(fid)] = {
        "rig_id": int(frame.rig_id),
        "images": sorted(int(d.id) for d in frame.image_ids),
    }

errors = []
colours = {}
for pid, point in rec.points3D.items():
    colours[str(pid)] = {
        "rgb": [int(c) for c in point.color],
        "images": [rec.images[el.image_id].name for el in point.track.elements],
    }
    for el in point.track.elements:
        img = rec.images[el.image_id]
        proj = img.project_point(point.xyz)
        if proj is None:
            errors.append(None)
            continue
        errors.append(float(np.linalg.norm(proj - img.points2D[el.point2D_idx].xy)))

print(json.dumps({
    "version": pycolmap.__version__,
    "cameras": cameras,
    "images": images,
    "rigs": rigs,
    "frames": frames,
    "points": len(rec.points3D),
    "errors": errors,
    "colours": colours,
}))

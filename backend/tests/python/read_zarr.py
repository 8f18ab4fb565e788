"""Open a UMI replay buffer (dataset.zarr.zip) with zarr-python and print, as JSON, every
array's path, dtype and shape, meta/episode_ends, and the non-image arrays' values (image
arrays: the mean of each frame). Used by backend/tests/export.rs.

Usage: python3 read_zarr.py dataset.zarr.zip
Exit status 3 when zarr is not installed (the test then skips with a message)."""
import json
import sys

try:
    import numpy as np
    import zarr
except ImportError:
    print("zarr is not installed (make deps installs it)", file=sys.stderr)
    sys.exit(3)

path = sys.argv[1]
if int(zarr.__version__.split(".")[0]) >= 3:
    store = zarr.storage.ZipStore(path, mode="r")
    root = zarr.open_group(store=store, mode="r", zarr_format=2)
else:
    store = zarr.ZipStore(path, mode="r")
    root = zarr.open_group(store=store, mode="r")

arrays = {}
for group in ("data", "meta"):
    for name, arr in root[group].arrays():
        key = f"{group}/{name}"
        data = np.asarray(arr[...])
        entry = {"dtype": str(data.dtype), "shape": list(data.shape)}
        if data.ndim == 4:
            entry["frame_means"] = data.reshape(data.shape[0], -1).mean(axis=1).tolist()
            entry["first_pixel"] = data[0, 0, 0].tolist() if data.shape[0] else []
        else:
            entry["values"] = data.tolist()
        entry["attrs"] = dict(arr.attrs)
        arrays[key] = entry
json.dump({"arrays": arrays}, sys.stdout)

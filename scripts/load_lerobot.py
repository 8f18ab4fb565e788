"""Load a KIWI LeRobot export with LeRobot itself, offline, and print what a policy would see.

    pip install lerobot==0.4.4        # the release that installs on Python 3.11 (pulls torch)
    kiwi export --session SESSION/session.toml --format lerobot --out DIR
    HF_HUB_OFFLINE=1 python3 scripts/load_lerobot.py DIR [--frame N]

Prints the dataset's episodes, rate, features and one frame: its state with the element names
of meta/info.json, its task and the shape of every camera image (decoded from the mp4 at the
row's timestamp, which LeRobot checks to within 1e-4 s), and the shapes of the statistics a
policy normalizes with."""
import argparse
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("root", help="the folder `kiwi export --format lerobot` wrote")
parser.add_argument("--frame", type=int, default=0, help="dataset index of the frame to print")
args = parser.parse_args()

ds = LeRobotDataset("local/kiwi", root=args.root)
print(f"{ds.num_episodes} episode(s), {ds.num_frames} frames at {ds.fps} Hz")
print("features:", ", ".join(ds.features))
item = ds[args.frame]
names = ds.features["observation.state"]["names"]
print(f"frame {args.frame}: episode {int(item['episode_index'])}, t = {float(item['timestamp']):.4f} s, task: {item['task']}")
for name, value in zip(names, item["observation.state"].tolist()):
    print(f"  {name:>16} = {value: .6f}")
for key in ds.meta.camera_keys:
    print(f"  {key}: {tuple(item[key].shape)}")
# The statistics a policy normalizes its inputs with: per element for the state, per colour
# channel (3, 1, 1) for each view.
for key in ["observation.state", *ds.meta.camera_keys]:
    s = ds.meta.stats[key]
    print(f"  stats {key}: mean shape {tuple(s['mean'].shape)}, count {int(s['count'][0])}")

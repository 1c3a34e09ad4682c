#!/usr/bin/env python3
"""rrd_screenshot: a PNG of a chunkrt recording as Rerun's own viewer draws it, in the recording's
own layout (chunkrt_record's: joints 0 and 1 commanded, measured and target with the predicted
chunks overlaid, the cameras, the controller's state, the log), the time cursor on a chunk switch.

The viewer runs headless (rerun-sdk's ``ViewerClient.spawn(headless=True)``); it needs a graphics
adapter, a GPU or Mesa's software Vulkan (lavapipe, Debian's ``mesa-vulkan-drivers``). Without a
Vulkan driver (no ICD manifest where the Vulkan loader looks) it says so and exits 3 at once,
without starting the viewer; a viewer that exits for want of an adapter also gives exit 3.

    python3 tools/python/rrd_screenshot.py run.rrd out.png [--joint 0] [--switch 0.5]
"""

import argparse
import os
import re
import socket
import sys
import tempfile
import time

import numpy as np
import rerun as rr
from rerun.experimental import ViewerClient

#: exit status when the viewer cannot start (no graphics adapter): nothing to screenshot with
NO_ADAPTER = 3

CHUNK = re.compile(r"joints/(\d+)/chunks/((\d+-)?\d+)")


def chunk_starts(path, joint):
    """The first robot time (ns) of each predicted chunk of `joint`, sorted."""
    starts = []
    for chunk in rr.chunk.RrdReader(path).stream():
        m = CHUNK.fullmatch(chunk.entity_path.lstrip("/"))
        if not m or int(m.group(1)) != joint or "robot_time" not in chunk.timeline_names:
            continue
        t = chunk.to_record_batch().column("robot_time").cast("int64").to_numpy(zero_copy_only=False)
        if len(t):
            starts.append(int(np.min(t)))
    return sorted(starts)


def viewer_alive(viewer):
    """Whether the spawned viewer process still runs (it exits when it cannot render)."""
    pid = getattr(viewer, "_pid", None)
    if pid is None:
        return True
    try:
        done, _ = os.waitpid(pid, os.WNOHANG)
        return done == 0
    except ChildProcessError:
        try:
            os.kill(pid, 0)
            return True
        except OSError:
            return False


def vulkan_drivers():
    """The Vulkan drivers (ICD manifests) the Vulkan loader would find: ``VK_DRIVER_FILES`` /
    ``VK_ICD_FILENAMES`` when set (they replace the search), else the manifests in the loader's
    directories. The viewer needs one; without, it panics after drawing nothing."""
    listed = os.environ.get("VK_DRIVER_FILES") or os.environ.get("VK_ICD_FILENAMES")
    if listed:
        return [p for p in listed.split(os.pathsep) if os.path.isfile(p)]
    dirs = [os.environ.get("XDG_CONFIG_HOME", os.path.expanduser("~/.config"))]
    dirs += (os.environ.get("XDG_CONFIG_DIRS") or "/etc/xdg").split(os.pathsep)
    dirs += ["/etc", os.environ.get("XDG_DATA_HOME", os.path.expanduser("~/.local/share"))]
    dirs += (os.environ.get("XDG_DATA_DIRS") or "/usr/local/share:/usr/share").split(os.pathsep)
    found = []
    for d in dirs:
        icd = os.path.join(d, "vulkan", "icd.d")
        if os.path.isdir(icd):
            found += [os.path.join(icd, f) for f in sorted(os.listdir(icd)) if f.endswith(".json")]
    return found


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rrd")
    ap.add_argument("png")
    ap.add_argument("--joint", type=int, default=0, help="the joint whose chunk switches are counted")
    ap.add_argument("--switch", type=float, default=0.5,
                    help="which chunk switch to centre, as a fraction of the run's chunks")
    ap.add_argument("--settle", type=float, default=6.0, help="seconds to let the viewer load")
    a = ap.parse_args()
    rrd = os.path.abspath(a.rrd)
    starts = chunk_starts(rrd, a.joint)
    if len(starts) < 2:
        print(f"{a.rrd}: fewer than two chunks of joint {a.joint}: no switch to show", file=sys.stderr)
        return 1
    at = starts[min(len(starts) - 1, max(1, int(a.switch * len(starts))))]
    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.gettempdir())
    # the viewer of this interpreter's rerun-sdk (its venv's bin/ need not be on PATH)
    exe = os.path.join(os.path.dirname(sys.executable), "rerun")
    why = ("it needs a graphics adapter: a GPU, or Mesa's software Vulkan "
           "(apt install mesa-vulkan-drivers)")
    if not vulkan_drivers():
        # without a Vulkan driver the viewer panics (a backtrace on stderr) before it draws
        print(f"rrd_screenshot: no Vulkan driver on this machine (no ICD manifest in the Vulkan "
              f"loader's directories, VK_DRIVER_FILES / VK_ICD_FILENAMES unset or empty); {why}",
              file=sys.stderr)
        return NO_ADAPTER
    try:
        viewer = ViewerClient.spawn(headless=True, port=free_port(), hide_welcome_screen=True,
                                    executable_path=exe if os.path.exists(exe) else None)
    except Exception as e:  # the viewer exits at once without a graphics adapter
        print(f"rrd_screenshot: the viewer did not start ({e}); {why}", file=sys.stderr)
        return NO_ADAPTER
    try:
        viewer.open(rrd)
        time.sleep(a.settle)
        viewer.set_time("robot_time", duration=at * 1e-9, play_state="paused")
        time.sleep(1.0)
        viewer.save_screenshot(os.path.abspath(a.png))
        # what the viewer itself holds of the file (not what this script read)
        schema = viewer.get_recording_schema(paths_only=True)
        paths = sorted(e.entity_path.lstrip("/") for e in schema.entities)
        held = sum(1 for p in paths if CHUNK.fullmatch(p))
        print(f"rrd_screenshot: the viewer holds {len(paths)} entities, {held} chunk series, "
              f"joints/0/measured {'yes' if 'joints/0/measured' in paths else 'NO'}")
    except ConnectionError as e:
        # a viewer that cannot render panics and exits, but not always before the failed
        # request returns: give it a few seconds to be gone
        deadline = time.monotonic() + 15.0  # slow to die on a loaded machine
        while viewer_alive(viewer) and time.monotonic() < deadline:
            time.sleep(0.1)
        if viewer_alive(viewer):
            raise  # the viewer refused what this script asked: a fault here, not the machine's
        print(f"rrd_screenshot: the viewer exited ({e}); {why}", file=sys.stderr)
        return NO_ADAPTER
    finally:
        try:
            viewer.quit()
        except Exception:
            pass
    print(f"rrd_screenshot: {a.png} (chunk switch at robot time {at * 1e-9:.3f} s, "
          f"{len(starts)} chunks of joint {a.joint})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

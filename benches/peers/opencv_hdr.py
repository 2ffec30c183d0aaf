#!/usr/bin/env python3
"""OpenCV peer for HDR merging (CalibrateDebevec + MergeDebevec) on the exact
inputs the depthgraph hdr_memorial bench wrote (same run, same machine).

Usage: opencv_hdr.py DIR [CASE ...]   (CASE: memorial, speed, or any NAME with DIR/NAME.json
  holding {"files", "times"} like memorial.json; default: memorial and speed)
  DIR/memorial.json: {"files": [png paths], "times": [seconds]}  (read with cv2.imread)
  DIR/speed.json:    {"width", "height", "times"} with DIR/speed.<j>.u8 (RGB 8-bit, row-major)
Each case present is run with two calibrations (OpenCV's defaults, and 400 samples with
lambda sqrt(1000), depthgraph's defaults in OpenCV's convention), merged with MergeDebevec.
Writes <case>.<method>.f32 (RGB float32 radiance, row-major) and <case>.peers.json
(ms, median of 3 runs for the calibration and 5 for the merge, after one untimed run).
Installs opencv-contrib-python-headless with pip when cv2 is missing.
"""
import json, os, sys

from peer_common import ensure_cv2, timed

def run_case(d, case, images, times):
    import cv2
    import numpy as np
    times = np.asarray(times, dtype=np.float32)
    calibrations = {
        "opencv_default": cv2.createCalibrateDebevec(),
        "opencv_400": cv2.createCalibrateDebevec(400, float(np.sqrt(1000.0)), False),
    }
    merge = cv2.createMergeDebevec()
    ms = {}
    for key, cal in calibrations.items():
        curve, ms[key + "_calibrate"] = timed(lambda: cal.process(images, times), 3, warmup=True)
        hdr, ms[key + "_merge"] = timed(lambda: merge.process(images, times, curve), 5, warmup=True)
        rgb = np.ascontiguousarray(hdr[:, :, ::-1], dtype="<f4")
        rgb.tofile(os.path.join(d, f"{case}.{key}.f32"))
    json.dump({"ms": ms, "opencv": cv2.__version__},
              open(os.path.join(d, case + ".peers.json"), "w"))
    print(case, {k: round(v, 2) for k, v in ms.items()})

def main(d, cases):
    ensure_cv2()
    import cv2
    import numpy as np
    cv2.setNumThreads(2)
    path = os.path.join(d, "memorial.json")
    if os.path.exists(path) and (not cases or "memorial" in cases):
        meta = json.load(open(path))
        images = [cv2.imread(f, cv2.IMREAD_COLOR) for f in meta["files"]]
        if any(i is None for i in images):
            sys.exit("memorial: cannot read some of " + ", ".join(meta["files"]))
        run_case(d, "memorial", images, meta["times"])
    for case in cases:
        if case in ("memorial", "speed"):
            continue
        path = os.path.join(d, case + ".json")
        if not os.path.exists(path):
            sys.exit(f"{case}: no {path}")
        meta = json.load(open(path))
        images = [cv2.imread(f, cv2.IMREAD_COLOR) for f in meta["files"]]
        if any(i is None for i in images):
            sys.exit(case + ": cannot read some of " + ", ".join(meta["files"]))
        run_case(d, case, images, meta["times"])
    path = os.path.join(d, "speed.json")
    if os.path.exists(path) and (not cases or "speed" in cases):
        meta = json.load(open(path))
        w, h = meta["width"], meta["height"]
        images = []
        for j in range(len(meta["times"])):
            rgb = np.fromfile(os.path.join(d, f"speed.{j}.u8"), dtype=np.uint8).reshape(h, w, 3)
            images.append(np.ascontiguousarray(rgb[:, :, ::-1]))
        run_case(d, "speed", images, meta["times"])

if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])

#!/usr/bin/env python3
"""OpenCV peers for the depth filters' speed, on the frames the depthgraph
depth_speed bench wrote (same run, same machine, 2 threads).

Usage: opencv_depth_speed.py DIR   (DIR holds <case>.json, <case>.depth.f32, <case>.color.u8)
Writes <case>.peers.json: {"ms": {method: median ms}, "opencv": version}.
Installs opencv-contrib-python-headless with pip when cv2 is missing.
"""
import json, os, sys

from peer_common import ensure_cv2, timed


def main(d):
    ensure_cv2()
    import cv2
    import numpy as np
    cv2.setNumThreads(2)
    for name in sorted(os.listdir(d)):
        if not name.endswith(".json") or name.endswith(".peers.json"):
            continue
        case = name[:-5]
        meta = json.load(open(os.path.join(d, name)))
        w, h, n = meta["width"], meta["height"], meta.get("repeats", 5)
        depth = np.fromfile(os.path.join(d, case + ".depth.f32"), dtype="<f4").reshape(h, w)
        rgb = np.fromfile(os.path.join(d, case + ".color.u8"), dtype=np.uint8).reshape(h, w, 3)
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        holes = (~np.isfinite(depth) | (depth <= 0)).astype(np.uint8)
        mm = np.clip(np.where(holes > 0, 0, depth) * 1000.0, 0, 65535).round().astype(np.uint16)
        ms = {}
        gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        _, ms["fastnlm_gray"] = timed(
            lambda: cv2.fastNlMeansDenoising(gray, h=10.0, templateWindowSize=7, searchWindowSize=21), n, True)
        _, ms["fastnlm_color"] = timed(lambda: cv2.fastNlMeansDenoising(bgr, h=10.0, templateWindowSize=7, searchWindowSize=21), n, True)
        _, ms["fastnlm_depth16"] = timed(
            lambda: cv2.fastNlMeansDenoising(mm, [30.0], None, 7, 21, cv2.NORM_L1), n, True)
        filled, ms["inpaint_ns"] = timed(lambda: cv2.inpaint(mm, holes, 5, cv2.INPAINT_NS), n, True)
        guide = bgr.astype(np.float32)
        zf = filled.astype(np.float32) / 1000.0
        _, ms["jbf9"] = timed(lambda: cv2.ximgproc.jointBilateralFilter(guide, zf, 9, 25.0, 3.0), n, True)
        _, ms["jbf15"] = timed(lambda: cv2.ximgproc.jointBilateralFilter(guide, zf, 15, 25.0, 3.0), n, True)
        json.dump({"ms": ms, "opencv": cv2.__version__}, open(os.path.join(d, case + ".peers.json"), "w"))
        print(case, {k: round(v, 2) for k, v in ms.items()})


if __name__ == "__main__":
    main(sys.argv[1])

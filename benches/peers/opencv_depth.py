#!/usr/bin/env python3
"""OpenCV peers for depth hole filling and smoothing, on the exact inputs the
depthgraph accuracy bench wrote (same run, same machine).

Usage: opencv_depth.py DIR   (DIR holds <case>.json, <case>.depth.f32, <case>.color.u8)
Writes <case>.<method>.f32 results and <case>.peers.json timings (ms, median of 3).
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
        w, h = meta["width"], meta["height"]
        depth = np.fromfile(os.path.join(d, case + ".depth.f32"), dtype="<f4").reshape(h, w)
        color = np.fromfile(os.path.join(d, case + ".color.u8"), dtype=np.uint8).reshape(h, w, 3)
        holes = (~np.isfinite(depth) | (depth <= 0)).astype(np.uint8)
        # cv2.inpaint's Telea overshoots badly on float32 depth (negative values, ~1 m RMSE
        # on our scenes); on 16-bit millimetres, the usual way to feed it depth, it is sane.
        src = np.clip(np.where(holes > 0, 0, depth) * 1000.0, 0, 65535).round().astype(np.uint16)
        res, timing = {}, {}
        for label, flag in (("opencv_telea", cv2.INPAINT_TELEA), ("opencv_ns", cv2.INPAINT_NS)):
            out, ms = timed(lambda: cv2.inpaint(src, holes, 5, flag), 3)
            res[label], timing[label] = out.astype(np.float32) / 1000.0, ms
        guide = cv2.cvtColor(color, cv2.COLOR_RGB2BGR).astype(np.float32)
        filled = res["opencv_telea"]
        sc, ss = meta.get("sigma_color_u8", 25.0), meta.get("sigma_space_px", 3.0)
        out, ms = timed(lambda: cv2.ximgproc.jointBilateralFilter(guide, filled, 11, sc, ss), 3)
        res["opencv_telea_jbf"], timing["opencv_telea_jbf"] = out, ms + timing["opencv_telea"]
        timing["opencv_jbf_only"] = ms
        out, ms = timed(lambda: cv2.ximgproc.guidedFilter(guide, filled, 5, 1e-4 * 255 * 255), 3)
        res["opencv_telea_guided"], timing["opencv_telea_guided"] = out, ms + timing["opencv_telea"]
        # fastGlobalSmootherFilter as a hole filler: the smoothed depth x mask over the
        # smoothed mask (normalised convolution), the known pixels kept as measured
        m = (holes == 0).astype(np.float32)
        zf = np.where(holes > 0, 0, depth).astype(np.float32)
        guide8 = cv2.cvtColor(color, cv2.COLOR_RGB2BGR)

        def fgs_fill():
            num = cv2.ximgproc.fastGlobalSmootherFilter(guide8, zf, 500.0, 10.0)
            den = cv2.ximgproc.fastGlobalSmootherFilter(guide8, m, 500.0, 10.0)
            out = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)
            return np.where(holes > 0, out, zf)
        res["opencv_fgs"], timing["opencv_fgs"] = timed(fgs_fill, 3)
        for k, v in res.items():
            np.asarray(v, dtype="<f4").tofile(os.path.join(d, f"{case}.{k}.f32"))
        json.dump({"ms": timing, "opencv": cv2.__version__}, open(os.path.join(d, case + ".peers.json"), "w"))
        print(case, {k: round(v, 2) for k, v in timing.items()})

if __name__ == "__main__":
    main(sys.argv[1])

#!/usr/bin/env python3
"""OpenCV peer for the copy-paste bench's edge stage, on the exact image the
depthgraph bench wrote (same run, same machine).

Usage: opencv_select.py DIR   (DIR holds color.u8 = W*H*3 bytes RGB and meta.json {width, height})
Prints one JSON line: medians (ms, of 5) of
  sobel:  3x3 cv2.Sobel in x and y on the 3 float32 channels + magnitude (the
          color half of our EdgeDetect),
  canny:  cv2.Canny on the grey image (thresholds 50, 150),
  seamless_clone: cv2.seamlessClone (NORMAL_CLONE) of a centred ellipse, the
          2D "paste + blend" a photo editor would use.
Installs opencv-contrib-python-headless with pip when cv2 is missing (as
opencv_depth.py does).
"""
import json, os, sys

from peer_common import ensure_cv2, timed

def main(d):
    ensure_cv2()
    import cv2
    import numpy as np
    cv2.setNumThreads(2)
    meta = json.load(open(os.path.join(d, "meta.json")))
    w, h = meta["width"], meta["height"]
    color = np.fromfile(os.path.join(d, "color.u8"), dtype=np.uint8).reshape(h, w, 3)
    f = color.astype(np.float32) / 255.0

    def sobel():
        gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
        return np.sqrt((gx * gx + gy * gy).sum(axis=2))
    _, ms_sobel = timed(sobel, 5)
    grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
    _, ms_canny = timed(lambda: cv2.Canny(grey, 50, 150), 5)
    mask = np.zeros((h, w), np.uint8)
    cv2.ellipse(mask, (w // 2, h // 2), (w // 8, h // 8), 0, 0, 360, 255, -1)
    _, ms_clone = timed(lambda: cv2.seamlessClone(color, color, mask, (w // 3, h // 2), cv2.NORMAL_CLONE), 5)
    print(json.dumps({"opencv": cv2.__version__, "sobel": ms_sobel, "canny": ms_canny,
                      "seamless_clone": ms_clone}))

if __name__ == "__main__":
    main(sys.argv[1])

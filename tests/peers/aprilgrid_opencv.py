"""Independent check of our AprilGrid target (issue 8): OpenCV's AprilTag 36h11 dictionary.

Usage: aprilgrid_opencv.py IMAGE.pgm N_TAGS

Prints one JSON line per tag id < N_TAGS with OpenCV's drawing of that tag as a 10 x 10 grid
of cells ({"marker": id, "cells": [[0|1]*10]*10}, 1 = white, 2-cell black border, row 0 at
the top), then one line per marker OpenCV detects in IMAGE ({"id": id, "corners":
[[u, v]*4]}, OpenCV's order: top-left, top-right, bottom-right, bottom-left of its own
drawing of the tag; pixel (0, 0) is the centre of the top-left pixel).
"""

import json
import sys

import cv2


def main() -> None:
    path, n_tags = sys.argv[1], int(sys.argv[2])
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for tag in range(n_tags):
        img = cv2.aruco.generateImageMarker(dictionary, tag, 10, borderBits=2)
        cells = [[int(img[r, c] > 127) for c in range(10)] for r in range(10)]
        print(json.dumps({"marker": tag, "cells": cells}))
    image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"cannot read {path}")
    params = cv2.aruco.DetectorParameters()
    params.markerBorderBits = 2
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(dictionary, params)
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return
    for quad, tag in zip(corners, ids.flatten()):
        print(json.dumps({"id": int(tag), "corners": quad.reshape(4, 2).tolist()}))


if __name__ == "__main__":
    main()

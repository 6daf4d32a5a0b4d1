"""Parse-only throughput of pygcode (https://pypi.org/project/pygcode/) on one file.

Called by gcode-bench with `--python PATH`; prints "<lines> <best seconds>".
Each line is parsed into words with pygcode.Line (no interpretation), best of 3.
"""
import sys
import time

from pygcode import Line


def main(path: str) -> None:
    with open(path, encoding="utf-8") as f:
        lines = f.read().splitlines()
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for text in lines:
            Line(text)
        best = min(best, time.perf_counter() - start)
    print(len(lines), best)


if __name__ == "__main__":
    main(sys.argv[1])

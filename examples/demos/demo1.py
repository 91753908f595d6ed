"""Runs the thesis' demonstration 1 on the simulators (the same as `temoto demo 1`).

Usage: python examples/demos/demo1.py [SPEED]   (SPEED: how much faster the robots' clocks run)
"""

import sys

from temoto.demos import run_demo

if __name__ == "__main__":
    speed = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
    sys.exit(0 if run_demo(1, speed=speed).ok else 1)

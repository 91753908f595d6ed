"""Load the machine with busy processes, for the load checks in docs/development.md.

    python tools/cpu_hog.py --factor 4 -- make run

starts ``factor x cores`` processes that spin at normal priority, runs the command, stops the
spinners and exits with the command's status. Without a command it spins until interrupted.
The load average (1 min) is printed every 30 s and at the end, so a report can say what load
the command really saw.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time


def _spin() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def _report(stop: threading.Event, every: float) -> None:
    while not stop.wait(every):
        print(f"cpu_hog: load average {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--factor", type=float, default=2.0, help="spinners per core (default 2)")
    parser.add_argument("--every", type=float, default=30.0, help="seconds between load lines")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="command to run under load")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    count = max(1, round(args.factor * (os.cpu_count() or 1)))
    spinners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(count)]
    for spinner in spinners:
        spinner.start()
    print(f"cpu_hog: {count} spinners on {os.cpu_count()} cores", file=sys.stderr, flush=True)
    stop = threading.Event()
    threading.Thread(target=_report, args=(stop, args.every), daemon=True).start()
    started = time.monotonic()
    status = 0
    try:
        if command:
            status = subprocess.call(command)
        else:
            stop.wait()
    except KeyboardInterrupt:
        status = 130
    finally:
        stop.set()
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.join()
    print(
        f"cpu_hog: {time.monotonic() - started:.1f} s, exit {status}, "
        f"load average {os.getloadavg()[0]:.1f}",
        file=sys.stderr,
        flush=True,
    )
    return status


if __name__ == "__main__":
    sys.exit(main())

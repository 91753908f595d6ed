"""Instructions per action of the engine's fast paths, counted by cachegrind (not timed).

Usage::

    python -m bench.instructions                     # this tree, every mode
    python -m bench.instructions --tree ../old chain-inline

Wall-clock figures on a shared 2-core machine spread by 2-4x between runs; an instruction count
does not. For each mode this runs a small engine workload under ``valgrind --tool=cachegrind
--cache-sim=no`` twice, with 1 and with 4 measured runs after two warm ones, and reports
(instructions of 4 runs - instructions of 1 run) / (3 x actions): the cost of one action with
start-up, imports and warm-up taken out. ``--tree`` points the workload at another checkout
(with its compiled kernels built), so two revisions can be compared on the same interpreter.

Modes: ``chain-inline`` and ``chain-blocking`` (2,000 actions in a row, inline or on a worker),
``fanout-inline`` (1,000 branches and their join). Needs valgrind (``apt-get install valgrind``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

MODES = {"chain-inline": 2000, "chain-blocking": 2000, "fanout-inline": 1001}
ROOT = Path(__file__).resolve().parent.parent

_WORKLOAD = """
import sys
from bench.common import chain_graph, fanout_graph
from bench.engine import BenchInline, BenchNoop, make_catalog
from temoto.core.engine import ActionEngine
from temoto.core.graph import parse_graph
from temoto.core.states import Result

mode, reps = sys.argv[1], int(sys.argv[2])
chain = mode.startswith("chain")
graph = parse_graph(chain_graph(2000) if chain else fanout_graph(1000))
noop = BenchNoop if mode.endswith("blocking") else BenchInline
engine = ActionEngine("bench", actions=make_catalog(noop))
try:
    for _ in range(reps + 2):  # two warm runs
        assert engine.wait(engine.start(graph), 600) is Result.TRUE
finally:
    engine.shutdown()
"""


def instructions(tree: Path, mode: str, reps: int) -> int:
    """Instructions (cachegrind's ``I refs``) of the workload with ``reps`` measured runs."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), str(ROOT)]))
    cmd = [
        "valgrind",
        "--tool=cachegrind",
        "--cache-sim=no",
        "--cachegrind-out-file=/dev/null",
        sys.executable,
        "-c",
        _WORKLOAD,
        mode,
        str(reps),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tree, check=False)
    found = re.search(r"I\s+refs:\s+([\d,]+)", done.stderr)
    if done.returncode != 0 or found is None:
        raise SystemExit(f"bench.instructions: {mode} failed:\n{done.stderr[-2000:]}")
    return int(found.group(1).replace(",", ""))


def main(argv: list[str] | None = None) -> int:
    """Print the instructions per action of each mode asked for."""
    parser = argparse.ArgumentParser(prog="python -m bench.instructions", description=__doc__)
    parser.add_argument("modes", nargs="*", metavar="MODE", help=", ".join(MODES))
    parser.add_argument("--tree", type=Path, default=ROOT, help="the checkout to measure")
    args = parser.parse_args(argv)
    if shutil.which("valgrind") is None:
        print("bench.instructions: needs valgrind (apt-get install valgrind)", file=sys.stderr)
        return 2
    unknown = [m for m in args.modes if m not in MODES]
    if unknown:
        parser.error(f"unknown mode {unknown[0]!r} (modes: {', '.join(MODES)})")
    tree = args.tree.resolve()
    for mode in args.modes or list(MODES):
        one, four = instructions(tree, mode, 1), instructions(tree, mode, 4)
        print(f"{mode}: {(four - one) // (3 * MODES[mode])} instructions per action ({tree})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Peer frameworks measured on the same machine, for scale.

Only runs what is importable; peers are never project dependencies (``pip install py_trees``
in the benchmark environment to enable the py_trees comparison).
"""

from __future__ import annotations

from bench.common import Results, median, now, repeat

SEQ_N = 1000


def bench_py_trees(quick: bool) -> Results:
    out = Results()
    try:
        import py_trees
    except ImportError:
        out.notes.append(
            "py_trees is not importable: peer_py_trees_seq_us_per_leaf skipped"
            " (pip install py_trees)"
        )
        return out
    try:
        from importlib.metadata import version

        ver = version("py_trees")
    except Exception:
        ver = "?"
    reps = 5 if quick else 30
    leaves = [py_trees.behaviours.Success(name=f"leaf_{i}") for i in range(SEQ_N)]
    root = py_trees.composites.Sequence(name="bench_seq", memory=True, children=leaves)
    root.setup_with_descendants()
    success = py_trees.common.Status.SUCCESS

    def once() -> float:
        t0 = now()
        root.tick_once()
        dt = now() - t0
        if root.status is not success or any(leaf.status is not success for leaf in leaves):
            raise RuntimeError("py_trees sequence did not tick every leaf to SUCCESS in one tick")
        return dt

    times = repeat(once, reps)
    out.add(
        "peer_py_trees_seq_us_per_leaf",
        median(times) / SEQ_N * 1e6,
        "us",
        f"py_trees {ver}: Sequence(memory=True) of {SEQ_N} Success leaves,"
        f" one tick_once() / {SEQ_N}; median of {reps}",
    )
    return out

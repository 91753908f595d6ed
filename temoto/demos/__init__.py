"""The thesis' demonstrations (§8), runnable on one machine with the simulators.

``temoto demo N`` (or :func:`run_demo`) runs demonstration N headless and prints a timeline a
person can follow; each returns a :class:`DemoReport` whose ``facts`` the tests check.

=====  ===================================  ==============================================
 N      demonstration                        module
=====  ===================================  ==============================================
 1      fault-tolerant sensor redundancy     :mod:`temoto.demos.sensor_redundancy`
 2      multi-robot escort                   :mod:`temoto.demos.escort`
 3      mission adaptiveness                 :mod:`temoto.demos.mission_adaptiveness`
 4      source-agnostic tasking              :mod:`temoto.demos.tasking`
 5      multi-robot knowledge sharing        :mod:`temoto.demos.knowledge_sharing`
=====  ===================================  ==============================================
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Mapping
from typing import IO, Final

from temoto.demos._timeline import DemoReport, Timeline

__all__ = ["DEMOS", "DemoReport", "Timeline", "run_demo"]

#: Demonstration number → (title, module).
DEMOS: Final[Mapping[int, tuple[str, str]]] = {
    1: ("Fault-tolerant sensor redundancy", "temoto.demos.sensor_redundancy"),
    2: ("Multi-robot escort", "temoto.demos.escort"),
    3: ("Mission adaptiveness", "temoto.demos.mission_adaptiveness"),
    4: ("Source-agnostic tasking", "temoto.demos.tasking"),
    5: ("Multi-robot knowledge sharing", "temoto.demos.knowledge_sharing"),
}


def run_demo(
    number: int,
    out: IO[str] | None = None,
    *,
    speed: float = 1.0,
    foxglove: tuple[str, int] | None = None,
    realism: str = "off",
    seed: int | None = None,
) -> DemoReport:
    """Run one demonstration and print its timeline.

    Args:
        number: 1 to 5.
        out: Where the timeline goes (default standard output).
        speed: How much faster than real time the robots' clocks run (tests use more than 1).
        foxglove: Serve the demonstration's displays live to Foxglove on this (host, port)
            (demonstrations 1 and 2), or None.
        realism: The simulated devices' realism level (``off``: the exact figures;
            ``typical``, ``harsh``: :mod:`temoto.drivers.realism`); demonstration 1 has none.
        seed: The realism's seed (None: a fresh one per robot at a level other than off).

    Returns:
        What happened, for checks.

    Raises:
        ValueError: No demonstration has that number, ``speed`` is not positive, or a server
            is asked of a demonstration without displays.
        ConfigError: The Foxglove SDK is missing, or the port cannot be listened on.
        ModuleNotFoundError: That demonstration is not built yet.
    """
    if number not in DEMOS:
        raise ValueError(f"no demonstration {number} (there are {', '.join(map(str, DEMOS))})")
    if not speed > 0:
        raise ValueError(f"speed must be positive, got {speed}")
    if foxglove is not None and number not in (1, 2):
        raise ValueError(f"--foxglove: demonstration {number} has no displays (1 and 2 have)")
    title, module_name = DEMOS[number]
    module = importlib.import_module(module_name)
    timeline = Timeline(out or sys.stdout, f"demo {number}: {title}")
    extra: dict[str, object] = {"foxglove": foxglove} if foxglove is not None else {}
    if number != 1:  # demonstration 1's sensors are processes, not simulated devices
        extra.update(realism=realism, seed=seed)
    report: DemoReport = module.run(timeline, speed=speed, **extra)
    timeline.close(report)
    return report

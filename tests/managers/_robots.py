"""A Robot Manager on its own registrar for the robot tests, torn down in full."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from temoto.clock import Clock
from temoto.config import Profile
from temoto.core.registrar import Registrar
from temoto.managers.robot import RobotManager


@contextmanager
def robot_manager(
    name: str, profile: Profile, clock: Clock | None = None, rate_hz: float = 50.0
) -> Iterator[tuple[Registrar, RobotManager]]:
    """A registrar named ``name`` serving ``profile``; every reference released at the end."""
    registrar = Registrar(name)
    manager = RobotManager(registrar, profile, clock=clock, rate_hz=rate_hz)
    try:
        yield registrar, manager
    finally:
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.shutdown()
        registrar.close()

"""Fleet authentication in tests: hand the members' hellos to one another by hand.

Tests of :class:`temoto.transport.auth.FleetAuth` run several members in one process with no
transport; :func:`settle` is the transport: it takes what each member publishes and opens it at
every other member, until nobody has anything more to say::

    alice = FleetAuth("fleet", "alice", KEY, clock=clock)
    bob = FleetAuth("fleet", "bob", KEY, clock=clock)
    settle(alice, bob)  # both hold each other's sessions now
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from temoto.transport.auth import FleetAuth

__all__ = ["settle"]


class _FakeClock(Protocol):
    """A test's wall clock: its time is the attribute ``t``, which the test moves."""

    t: float


def settle(*members: FleetAuth, clock: _FakeClock | None = None, rounds: int = 20) -> None:
    """Hand everything each member publishes to every other one until nothing is left.

    Args:
        *members: The members, each a :class:`~temoto.transport.auth.FleetAuth`.
        clock: The members' fake clock; when given, it is moved on to a member's next hello
            whenever one is due later (members that hold a hello back then send it).
        rounds: How many rounds (every member's output handed on) before giving up.

    Raises:
        AssertionError: The members still had something to say after ``rounds`` rounds.
    """
    for _ in range(rounds):
        moved = False
        for member in members:
            if clock is not None:
                due = member.hello_due_in()
                if due:
                    clock.t += due + 1e-6
            for channel, data in member.take_outgoing():
                moved = True
                for other in members:
                    if other is not member:
                        other.open(channel, data)
        if not moved:
            return
    raise AssertionError("the hellos never settled")

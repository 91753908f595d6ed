"""Effects: what the engine decided under its lock and carries out once the lock is released.

Evolution (:mod:`temoto.core.evolution`) never runs user code, waits or calls out while it holds
the engine's lock; each thing to do outside the lock goes into an :class:`Effects` collection,
and the dispatcher (:mod:`temoto.core.dispatch`) carries it out: actions and hooks on the
worker pool, calls to the actor link in the calling thread.

Two kinds of entries:

* **Runs** (``Effects.runs``): an action to run, as the pair ``(node, generation)``. There is
  one per action run, the engine's most frequent effect, so a run costs a plain pair: a record
  of its own (a named tuple is a subclass of tuple) costs several times more to make, measured
  as a few percent of a chain's time per action.
* **Everything else** (``Effects.other``): an :class:`Effect` record whose :class:`EffectKind`
  says what to do (a hook, a release, the end of a spontaneous action's run, a call to the
  actor link), with the fields that kind uses.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from temoto.core._runtime import Node
    from temoto.core.action import Action
    from temoto.core.states import Result

__all__ = ["Effect", "EffectKind", "Effects", "Ending", "Run"]

#: How an action run ended: its result, its outputs and its error (or None).
Ending = tuple["Result", dict[str, Any], BaseException | None]
#: An action to run: its node and the node's run generation it was decided for (an entry meant
#: for an earlier run is dropped).
Run = tuple["Node", int]


class EffectKind(Enum):
    """What an effect does."""

    __hash__ = object.__hash__  # members are singletons; Enum's own hash is slow Python code

    #: Call the hook named ``hook`` (``on_stop``, ``on_pause``, ``on_resume``) on a worker.
    HOOK = "hook"
    #: On a worker, stop what runs downstream of the spontaneous action ``node``, then apply
    #: its ``ending`` and run it again.
    FINISH_SPONTANEOUS = "finish_spontaneous"
    #: Release the resources ``action`` acquired, on a worker.
    RELEASE = "release"
    #: Make the short call ``call(*args)`` to the actor link, in the dispatching thread.
    CALL = "call"


class Effect(NamedTuple):
    """One thing to do once the engine's lock is released.

    Attributes:
        kind: What to do.
        node: The node it concerns (HOOK, FINISH_SPONTANEOUS).
        gen: The node's run generation it was decided for: an effect meant for an earlier run
            is dropped.
        hook: The hook's name (HOOK).
        ending: How the run ended (FINISH_SPONTANEOUS).
        action: The action instance whose resources to release (RELEASE).
        call: The function to call (CALL).
        args: Its arguments (CALL).
    """

    kind: EffectKind
    node: Node | None = None
    gen: int = 0
    hook: str = ""
    ending: Ending | None = None
    action: Action | None = None
    call: Callable[..., object] | None = None
    args: tuple[Any, ...] = ()


class Effects:
    """The effects decided under the lock, in the order they were decided (per kind).

    Attributes:
        runs: Actions to run, as ``(node, gen)`` pairs.
        other: Every other effect.
    """

    __slots__ = ("other", "runs")

    def __init__(self) -> None:
        self.runs: list[Run] = []
        self.other: list[Effect] = []

    def __bool__(self) -> bool:
        return bool(self.runs or self.other)

    def __repr__(self) -> str:
        return f"Effects(runs={len(self.runs)}, other={[e.kind.value for e in self.other]})"

    def clear(self) -> None:
        """Forget every effect (a worker reuses one collection per round).

        Returns:
            None.
        """
        self.runs.clear()
        self.other.clear()

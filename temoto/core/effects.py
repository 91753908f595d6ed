"""Effects: what the engine decided under its lock and carries out once the lock is released.

Evolution (:mod:`temoto.core.evolution`) never runs user code, waits or calls out while it holds
the engine's lock; each thing to do outside the lock is appended to an effect list as an
:class:`Effect`, and the dispatcher (:mod:`temoto.core.dispatch`) carries the list out: actions
and hooks on the worker pool, calls to the actor link in the calling thread.

An effect is a small record (a named tuple: about as cheap to make as a plain tuple, and read
by field name); which fields are set depends on its :class:`EffectKind`.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from temoto.core._runtime import Node
    from temoto.core.action import Action
    from temoto.core.states import Result

__all__ = ["Effect", "EffectKind", "Ending"]

#: How an action run ended: its result, its outputs and its error (or None).
Ending = tuple["Result", dict[str, Any], BaseException | None]


class EffectKind(Enum):
    """What an effect does."""

    __hash__ = object.__hash__  # members are singletons; Enum's own hash is slow Python code

    #: Run the action of ``node`` (run generation ``gen``) on a worker.
    RUN = "run"
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
        node: The node it concerns (RUN, HOOK, FINISH_SPONTANEOUS).
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

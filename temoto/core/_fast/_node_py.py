"""The node kernel: a node's fields as one record, and the chain loop that works on them.

Canonical source of two builds: imported as is (the pure build), and compiled by Cython as
``_node_c`` with the declarations in ``_node_c.pxd`` (STYLE.md 3.9), where the records are C
structs (extension types) and the loop reads and writes their fields directly instead of
through attribute lookups. Import it only through :mod:`temoto.core._fast`.

- :class:`ControlCore` holds a node's stop and pause signals (the fields of
  :class:`~temoto.core.control.RunControl`, which adds the behaviour).
- :class:`NodeCore` adds the node's run state (the fields of
  :class:`~temoto.core._runtime.Node`, which adds the behaviour).
- :func:`run_chain` is the engine's loop for a chain of actions
  (``EffectDispatcher._run_chain``, :mod:`temoto.core.dispatch`): it runs an action, applies
  its common end and starts the one child it made ready, on the calling thread, and hands
  everything else back to the engine's general path.

Every field is guarded by the engine's lock, as before; this module only changes where the
fields live.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import threading

    from temoto.clock import Clock

__all__ = ["ControlCore", "NodeCore", "run_chain"]


class ControlCore:
    """The fields of a node's stop and pause signals (no behaviour: see ``RunControl``)."""

    __slots__ = ("acquired", "broken", "clock", "condition", "logged", "paused", "stop")

    acquired: bool
    broken: list[Any] | None
    clock: Clock
    condition: threading.Condition | None
    logged: bool
    paused: bool
    stop: bool


class NodeCore(ControlCore):
    """The fields of a graph run's node (no behaviour: see ``Node``)."""

    __slots__ = (
        "child_run",
        "cls",
        "data",
        "error",
        "fresh_instance",
        "gen",
        "held",
        "idx",
        "inline",
        "inputs",
        "instance",
        "kind",
        "last_outputs",
        "log",
        "name",
        "native",
        "outputs",
        "plan",
        "remote_cancel",
        "required_inputs",
        "restart",
        "run",
        "spontaneous",
        "state",
        "stop_timer",
        "umrf",
    )

    child_run: Any
    cls: Any
    data: Any
    error: Any
    fresh_instance: Any
    gen: Any
    held: Any
    idx: Any
    inline: Any
    inputs: Any
    instance: Any
    kind: Any
    last_outputs: Any
    log: Any
    name: Any
    native: Any
    outputs: Any
    plan: Any
    remote_cancel: Any
    required_inputs: Any
    restart: Any
    run: Any
    spontaneous: Any
    state: Any
    stop_timer: Any
    umrf: Any


def run_chain(
    engine: Any,
    node: NodeCore,
    gen: Any,
    instance: Any,
    values: Any,
    fx: Any,
    todo: list[Any],
    k: tuple[Any, ...],
) -> None:
    """The engine's chain loop: rounds of one action each, for as long as they last.

    What ``EffectDispatcher._run_chain`` documents (:mod:`temoto.core.dispatch`), which calls
    this with the engine (the dispatcher), the first action's run and the constants ``k``
    (``EffectDispatcher._chain_constants``). Returns (the engine's lock released) as soon as a
    round is anything but the common end of an action that starts one idle local child,
    leaving ``fx`` and ``todo`` as the engine's round would have.

    Args:
        engine: The dispatcher (its lock, its general path, its observers).
        node: The node whose run comes first.
        gen: That run's generation.
        instance: The node's action instance, or None to make one.
        values: The run's input values.
        fx: The dispatcher's effects (empty on entry).
        todo: Where the runs this thread goes on with are left.
        k: The engine's constants: node states RUNNING and FINISHED, graph state RUNNING,
            local node kind, active node states, result ERROR, the codes of results, no values,
            ``SHIFT``, the wave step of a ready and of a waiting `run`, parameter transfer and
            the error of a failed initialisation.

    Returns:
        None.

    Raises:
        Nothing but what the engine's own calls raise.
    """
    (
        running,
        finished,
        graph_running,
        local,
        active,
        result_error,
        result_codes,
        no_values,
        shift,
        run_ready,
        run_waits,
        transfer,
        init_error,
    ) = k
    lock = engine._lock
    acquire = lock.acquire
    release = lock.release
    runs = fx.runs
    other = fx.other
    while True:
        if instance is None:
            try:
                instance = engine._instantiate(node, gen)
            except Exception as err:
                with lock:
                    engine._settle(
                        (node, gen, None, result_error, no_values, init_error(node, err)), fx
                    )
                    engine._collect(fx, todo)
                return
        result, outputs, error = instance.run_once(values)
        acquire()  # not `with lock`: its __enter__ and __exit__ cost as much again
        try:
            run = node.run
            if not (
                error is None
                and gen == node.gen
                and node.state is running
                and run.state is graph_running
                and not engine._watchers
                and not engine._feedback_on
                and not node.restart
                and not node.spontaneous
                and node.stop_timer is None
            ):
                engine._settle((node, gen, instance, result, outputs, error), fx)
                engine._collect(fx, todo)
                return
            # what _run_batch does for a round's common end, for this one action
            if node.instance is None:
                node.instance = instance
            if node.log or node.logged:
                node.log = instance.log_snapshot()
            data = node.data
            if len(data) != len(node.native):
                node.clear_data()  # type: ignore[attr-defined]  # Node's behaviour
            node.last_outputs = outputs
            node.state = finished  # RUNNING -> FINISHED, in a RUNNING graph
            run.active -= 1
            if engine._quiet_waiters:
                engine._quiet.notify_all()
            evolution = run.evolution
            code = result_codes[result]
            step = evolution.advance(node.idx, code)  # the kernel's wave, if one step
            child: Any = None
            if step >= 0 and step & 1:
                # one relation, whose response is `run`, to a child with every parent
                edge = step >> 1
                child = run.edge_child[edge]
                if outputs:
                    transfer(node, child, run.edge_remap[edge], outputs)
                if not (
                    child.kind is local  # inline or blocking: it runs next, here
                    and child.state not in active
                    and (not child.required_inputs or child.inputs_ready())
                ):
                    child = None
                    steps = [edge << shift | run_ready]
                    engine._apply_wave(node, result, no_values, steps, fx)  # done: transfer
            elif step >= 0:  # one step to a child that waits for other parents
                steps = [(step >> 1) << shift | run_waits]
                engine._apply_wave(node, result, outputs, steps, fx)
            else:
                engine._apply_wave(node, result, outputs, evolution.propagate(node.idx, code), fx)
            if child is not None:
                # _apply_wave's start of an idle local node
                child.gen += 1
                child.held = None
                if child.condition is None:  # RunControl.reset, nobody waits to race with
                    child.stop = False
                    child.paused = False
                else:
                    child.reset()  # RunControl's behaviour
                if child.fresh_instance:
                    child.instance = None  # the old one is stuck in a run we gave up on
                    child.fresh_instance = False
                child.state = running
                run.active += 1
                data = child.data
                if other or engine._releases:  # effects to dispatch first: back to the round
                    todo.append(
                        (child, child.gen, child.instance, dict(data) if data else no_values)
                    )
                    return
                node = child
                gen = child.gen
                instance = child.instance
                values = dict(data) if data else no_values
                continue
            if not run.active:
                engine._after_change(run, fx)
            if len(runs) == 1 and not other:  # the next link of the chain, made by the wave
                child, child_gen = runs[0]
                if (
                    child.inline
                    and child_gen == child.gen
                    and child.state is running
                    and not child.run.peers  # (a sub-graph's end may reach a shared run)
                ):
                    runs.clear()
                    data = child.data
                    node = child
                    gen = child_gen
                    instance = child.instance
                    values = dict(data) if data else no_values
                    continue
            engine._collect(fx, todo)
            return
        finally:
            release()

"""The evolution kernel: how a finished action's result reaches its children (thesis §6.1.4).

Canonical source of two builds: imported as is (the pure build), and compiled by Cython as
``_evolution_c`` with the declarations in ``_evolution_c.pxd`` (docs/development.md §7).
Import it only through :mod:`temoto.core._fast`.

Everything here is integers in flat arrays; the engine numbers a graph run's nodes
``0 .. n-1`` when it wires the run and keeps names, data and action instances to itself.

- **Edges** are the parent -> child relations, grouped by parent: the edges of node ``p`` are
  ``edge_start[p] .. edge_start[p + 1] - 1``. Each edge has a child, a *slot* and a row of
  responses, one per result code (``edge_response[e * N_RESULTS + result]``); responses the
  graph does not write are filled in by :func:`default_response`.
- **Slots** are the distinct (child, parent) pairs, grouped by child: the slots of node ``c``
  are ``slot_start[c] .. slot_start[c + 1] - 1``. A slot remembers whether its parent was
  received (finished at least once in this run) and whether it is required; a node's
  ``missing`` count is its number of required slots not received yet.

Codes (the order of the enums in :mod:`temoto.core.states`):

- results ``R_TRUE, R_FALSE, R_STOPPED, R_ERROR``;
- responses ``P_RUN, P_PAUSE, P_RESTART, P_STOP, P_BYPASS, P_IGNORE``, and ``P_LOOP`` for a
  bypass that comes back to a node it already bypassed in the same wave;
- parent states for eq. 6.1 ``S_IDLE_TRUE, S_IDLE_FALSE, S_STOPPED, S_ERROR, S_OTHER``.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence

__all__ = [
    "N_RESULTS",
    "N_STATES",
    "P_BYPASS",
    "P_IGNORE",
    "P_LOOP",
    "P_PAUSE",
    "P_RESTART",
    "P_RUN",
    "P_STOP",
    "R_ERROR",
    "R_FALSE",
    "R_STOPPED",
    "R_TRUE",
    "SHIFT",
    "S_ERROR",
    "S_IDLE_FALSE",
    "S_IDLE_TRUE",
    "S_OTHER",
    "S_STOPPED",
    "V_ERROR",
    "V_NONE",
    "V_RUN",
    "Evolution",
    "default_evolution",
    "default_response",
]

R_TRUE = 0
R_FALSE = 1
R_STOPPED = 2
R_ERROR = 3
N_RESULTS = 4

P_RUN = 0
P_PAUSE = 1
P_RESTART = 2
P_STOP = 3
P_BYPASS = 4
P_IGNORE = 5
P_LOOP = 6

S_IDLE_TRUE = 0
S_IDLE_FALSE = 1
S_STOPPED = 2
S_ERROR = 3
S_OTHER = 4
N_STATES = 5

#: Outcomes of eq. 6.1: the child evolves to running, to error, or not at all.
V_NONE = 0
V_RUN = 1
V_ERROR = 2

#: The wave counter starts over (and the marks are cleared) when it reaches this.
WAVE_LIMIT = 1 << 30

#: A step of a wave is packed as ``edge << SHIFT | response << 1 | ready``.
SHIFT = 4


def default_evolution(rows: array[int], n_rows: int) -> int:
    """Eq. 6.1: the default evolution of a child from its parents' one-hot state rows.

    ``s = s_r^T [max(sign(1 S s_idx) - sign(1 S s_e), 0)] + s_e^T sign(1 S s_e)``: the child
    runs if any parent is idle-true or idle-false and none is in error, goes to error if any
    parent is in error, and otherwise does not evolve.

    Args:
        rows: ``n_rows * N_STATES`` zeros and ones as signed bytes (``array("b")`` or any
            buffer of format ``b``), row-major; row ``i`` is parent ``i``'s state one-hot over
            ``S_IDLE_TRUE .. S_OTHER``.
        n_rows: Number of parents.

    Returns:
        ``V_RUN``, ``V_ERROR`` or ``V_NONE``.

    Raises:
        TypeError: ``rows`` is not a buffer.
        ValueError: ``rows`` is not of format ``b`` or is shorter than ``n_rows * N_STATES``.
    """
    if memoryview(rows).format != "b":
        raise ValueError("rows must be a buffer of signed bytes (format 'b')")
    # the constants as locals: typed ints in the compiled build, no global lookups per row
    n_states = N_STATES
    idle_true = S_IDLE_TRUE
    idle_false = S_IDLE_FALSE
    in_error = S_ERROR
    if n_rows < 0 or len(rows) < n_rows * n_states:
        raise ValueError(f"need {n_rows} rows of {n_states} columns, got {len(rows)} values")
    idle = 0  # 1 S s_idx: how many parents are idle (true or false)
    error = 0  # 1 S s_e: how many parents are in error
    i = 0
    while i < n_rows:
        base = i * n_states
        idle += rows[base + idle_true] + rows[base + idle_false]
        error += rows[base + in_error]
        i += 1
    if error > 0:
        return V_ERROR
    if idle > 0:
        return V_RUN
    return V_NONE


def default_response(result: int) -> int:
    """The response of a relation the graph wrote no condition for (docs/design.md §4.3).

    Eq. 6.1 over the one row of the parent that just finished: idle-true or idle-false runs the
    child; error evolves it to error, which the engine carries out as ``bypass`` (the child is
    skipped and the error travels on); a stopped parent leaves it alone (``ignore``).

    Args:
        result: A result code (``R_TRUE`` .. ``R_ERROR``).

    Returns:
        A response code.

    Raises:
        ValueError: Unknown result code.
    """
    if result == R_TRUE:
        state = S_IDLE_TRUE
    elif result == R_FALSE:
        state = S_IDLE_FALSE
    elif result == R_STOPPED:
        state = S_STOPPED
    elif result == R_ERROR:
        state = S_ERROR
    else:
        raise ValueError(f"unknown result code {result}")
    row = array("b", bytes(N_STATES))
    row[state] = 1
    verdict = default_evolution(row, 1)
    if verdict == V_RUN:
        return P_RUN
    if verdict == V_ERROR:
        return P_BYPASS
    return P_IGNORE


def _int_array(values: Sequence[int], what: str) -> array[int]:
    try:
        return array("i", values)
    except (TypeError, OverflowError) as err:
        raise ValueError(f"{what}: {err}") from None


class Evolution:
    """The integer topology and received-state of one graph run.

    Args:
        n_nodes: Number of nodes (``0 .. n_nodes - 1``).
        edge_start: ``n_nodes + 1`` offsets into the edge arrays, by parent.
        edge_child: The child of each edge.
        edge_slot: The (child, parent) slot of each edge.
        edge_response: ``N_RESULTS`` response codes per edge; ``-1`` means "no condition
            written": the default (:func:`default_response`) is filled in.
        slot_start: ``n_nodes + 1`` offsets into the slot arrays, by child.
        slot_required: 1 if the slot's parent is required.
        exit_node: The node whose readiness (or a bypass into it) ends the run; -1 for none.
        received: Initial received flag per slot (a re-wired run keeps what it received);
            all zero if omitted.

    Raises:
        ValueError: Inconsistent arrays (wrong lengths, out-of-range ids or codes).
    """

    def __init__(
        self,
        n_nodes: int,
        edge_start: Sequence[int],
        edge_child: Sequence[int],
        edge_slot: Sequence[int],
        edge_response: Sequence[int],
        slot_start: Sequence[int],
        slot_required: Sequence[int],
        exit_node: int = -1,
        received: Sequence[int] | None = None,
    ) -> None:
        if n_nodes < 0:
            raise ValueError(f"n_nodes must be >= 0, not {n_nodes}")
        n_edges = len(edge_child)
        n_slots = len(slot_required)
        if len(edge_start) != n_nodes + 1 or len(slot_start) != n_nodes + 1:
            raise ValueError("edge_start and slot_start need n_nodes + 1 offsets")
        if len(edge_slot) != n_edges or len(edge_response) != n_edges * N_RESULTS:
            raise ValueError("edge_slot needs one value and edge_response four per edge")
        if edge_start[0] != 0 or edge_start[n_nodes] != n_edges:
            raise ValueError("edge_start must run from 0 to the number of edges")
        if slot_start[0] != 0 or slot_start[n_nodes] != n_slots:
            raise ValueError("slot_start must run from 0 to the number of slots")
        if not -1 <= exit_node < n_nodes:
            raise ValueError(f"exit node {exit_node} out of range")
        for i in range(n_nodes):
            if edge_start[i] > edge_start[i + 1] or slot_start[i] > slot_start[i + 1]:
                raise ValueError(f"offsets of node {i} decrease")
        for e in range(n_edges):
            child = edge_child[e]
            if not 0 <= child < n_nodes:
                raise ValueError(f"edge {e}: child {child} out of range")
            if not slot_start[child] <= edge_slot[e] < slot_start[child + 1]:
                raise ValueError(f"edge {e}: slot {edge_slot[e]} is not a slot of node {child}")
        responses = [default_response(r) for r in range(N_RESULTS)]
        filled = list(edge_response)
        for k in range(n_edges * N_RESULTS):
            code = filled[k]
            if code == -1:
                filled[k] = responses[k % N_RESULTS]
            elif not P_RUN <= code <= P_IGNORE:
                raise ValueError(f"edge {k // N_RESULTS}: unknown response code {code}")
        if received is None:
            flags = array("b", bytes(n_slots))
        elif len(received) != n_slots:
            raise ValueError("received needs one flag per slot")
        else:
            flags = array("b", [1 if f else 0 for f in received])
        missing = array("i", bytes(4 * n_nodes))
        for c in range(n_nodes):
            for s in range(slot_start[c], slot_start[c + 1]):
                if slot_required[s] and not flags[s]:
                    missing[c] += 1
        self.n_nodes = n_nodes
        self.edge_start = _int_array(edge_start, "edge_start")
        self.edge_child = _int_array(edge_child, "edge_child")
        self.edge_slot = _int_array(edge_slot, "edge_slot")
        self.edge_response = array("b", filled)
        self.slot_start = _int_array(slot_start, "slot_start")
        self.slot_required = array("b", [1 if r else 0 for r in slot_required])
        self.received = flags
        self.missing = missing
        self.exit_node = exit_node
        self.wave = 0  # number of the current wave, for the bypass marks
        self.marks = array("i", bytes(4 * n_nodes))  # wave in which a node was bypassed
        self.queue = array("i", bytes(4 * (n_nodes + 1)))  # nodes whose results travel on

    def propagate(self, parent: int, result: int) -> list[int]:
        """A parent finished with ``result``: one evolution wave through its children.

        Every child marks the parent received and looks up its response. A ``bypass`` response
        marks the child bypassed and sends the same result on to the child's own children,
        within this wave; a bypass that reaches a node already bypassed in this wave is
        reported as ``P_LOOP`` and goes no further. The wave ends early at the exit node when
        a bypass reaches it, or when it is ready and does not ignore the result.

        Args:
            parent: The finished node.
            result: Its result code.

        Returns:
            The steps in order, each packed as ``edge << SHIFT | response << 1 | ready``;
            ``ready`` means every required parent of the edge's child has been received (the
            engine still checks required inputs). The caller carries out each step.

        Raises:
            IndexError: Unknown node.
            ValueError: Unknown result code.
        """
        if not 0 <= parent < self.n_nodes:
            raise IndexError(f"node {parent} out of range")
        if not 0 <= result < N_RESULTS:
            raise ValueError(f"unknown result code {result}")
        if self.wave >= WAVE_LIMIT:  # keep the counter far from overflow in the C build
            for i in range(self.n_nodes):
                self.marks[i] = 0
            self.wave = 0
        self.wave += 1
        wave = self.wave
        # the constants as locals: typed ints in the compiled build, no global lookups per edge
        n_results = N_RESULTS
        shift = SHIFT
        bypass = P_BYPASS
        loop = P_LOOP
        ignore = P_IGNORE
        exit_node = self.exit_node
        out: list[int] = []
        self.queue[0] = parent
        head = 0
        tail = 1
        while head < tail:
            node = self.queue[head]
            head += 1
            e = self.edge_start[node]
            end = self.edge_start[node + 1]
            while e < end:
                child = self.edge_child[e]
                slot = self.edge_slot[e]
                if not self.received[slot]:
                    self.received[slot] = 1
                    if self.slot_required[slot]:
                        self.missing[child] -= 1
                response = self.edge_response[e * n_results + result]
                ready = 1 if self.missing[child] == 0 else 0
                if response == bypass and child != exit_node:
                    if self.marks[child] == wave:
                        response = loop
                    else:
                        self.marks[child] = wave
                        self.queue[tail] = child
                        tail += 1
                out.append((e << shift) | (response << 1) | ready)
                if child == exit_node and (
                    response == bypass or (ready == 1 and response != ignore)
                ):
                    return out
                e += 1
        return out

    def advance(self, parent: int, result: int) -> int:
        """:meth:`propagate` for a wave of one `run` step: a chain's link, a fan-in's edge.

        When ``parent`` has exactly one relation, its response to ``result`` is ``run`` and its
        child is not the exit node, the wave is that one step: the parent is marked received
        (as :meth:`propagate` does) and the step is returned as ``edge << 1 | ready``, with no
        list made (``ready``: every required parent of the child has been received). In every
        other case nothing changes and -1 is returned: the caller then calls
        :meth:`propagate`, whose result is the same as if this method had not been called.

        Args:
            parent: The finished node.
            result: Its result code.

        Returns:
            ``edge << 1 | ready`` for the one step, or -1.

        Raises:
            IndexError: Unknown node.
            ValueError: Unknown result code.
        """
        if not 0 <= parent < self.n_nodes:
            raise IndexError(f"node {parent} out of range")
        if not 0 <= result < N_RESULTS:
            raise ValueError(f"unknown result code {result}")
        n_results = N_RESULTS  # the constants as locals: typed ints in the compiled build
        run = P_RUN
        e = self.edge_start[parent]
        if self.edge_start[parent + 1] != e + 1:
            return -1  # not one relation
        if self.edge_response[e * n_results + result] != run:
            return -1
        child = self.edge_child[e]
        if child == self.exit_node:
            return -1
        slot = self.edge_slot[e]
        if not self.received[slot]:
            self.received[slot] = 1
            if self.slot_required[slot]:
                self.missing[child] -= 1
        return (e << 1) | (1 if self.missing[child] == 0 else 0)

    def missing_parents(self, node: int) -> int:
        """How many required parents of ``node`` were not received yet.

        Args:
            node: The node.

        Returns:
            The count.

        Raises:
            IndexError: Unknown node.
        """
        if not 0 <= node < self.n_nodes:
            raise IndexError(f"node {node} out of range")
        return self.missing[node]

    def received_any(self, node: int) -> bool:
        """Whether any parent of ``node`` was received in this run.

        Args:
            node: The node.

        Returns:
            True if at least one was.

        Raises:
            IndexError: Unknown node.
        """
        if not 0 <= node < self.n_nodes:
            raise IndexError(f"node {node} out of range")
        s = self.slot_start[node]
        end = self.slot_start[node + 1]
        while s < end:
            if self.received[s]:
                return True
            s += 1
        return False

    def fresh(self) -> Evolution:
        """A kernel of the same graph in which nothing was received yet: a new run's.

        The graph's arrays (edges, slots, responses), which no kernel ever writes, are shared
        with this one, already checked and converted; the run's state (received flags,
        missing counts, bypass marks) is new. A repeated run of a plan starts from it without
        the constructor's work per edge.

        Returns:
            The new kernel.
        """
        new = Evolution.__new__(Evolution)
        n = self.n_nodes
        n_slots = self.slot_start[n]
        new.n_nodes = n
        new.edge_start = self.edge_start
        new.edge_child = self.edge_child
        new.edge_slot = self.edge_slot
        new.edge_response = self.edge_response
        new.slot_start = self.slot_start
        new.slot_required = self.slot_required
        new.received = array("b", bytes(n_slots))
        new.missing = array("i", bytes(4 * n))
        for c in range(n):
            s = self.slot_start[c]
            end = self.slot_start[c + 1]
            while s < end:
                if self.slot_required[s]:
                    new.missing[c] += 1
                s += 1
        new.exit_node = self.exit_node
        new.wave = 0
        new.marks = array("i", bytes(4 * n))
        new.queue = array("i", bytes(4 * (n + 1)))
        return new

    def received_flags(self) -> bytes:
        """The received flag of every slot (to carry over into a re-wired run).

        Returns:
            One byte (0 or 1) per slot.
        """
        return bytes(self.received)

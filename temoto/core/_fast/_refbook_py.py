"""The registrar's reference-count and dependency book: integer slots in flat arrays.

The canonical, pure-Python implementation. ``setup.py`` compiles this same file with Cython as
``temoto.core._fast._refbook_c``, and ``_refbook_c.pxd`` turns :class:`RefBook` into a ``cdef
class`` whose arrays are typed memoryviews (docs/development.md §7). Import it only through
``temoto.core._fast``.

Only integers cross the boundary. A *resource* is a slot number; a *reference* is another slot
number, naming the resource it counts and its *holder*: the resource slot that owns it as a
dependency, or ``-1`` for a consumer's reference. Each resource keeps its dependency references
in a doubly linked list (previous/next slot), so acquiring and releasing are O(1) and
:meth:`RefBook.dependencies` lists them in acquisition order. Freed slots are reused, last freed
first. What the slots mean (ids, callbacks, priorities) is the caller's business
(:class:`temoto.core.registrar.Registrar`).

Layout: one ``array('i')`` of resource records and one of reference records, each record a few
consecutive fields (``slot * FIELDS + field``), so one slot's fields sit side by side in memory.
"""

from __future__ import annotations

from array import array

__all__ = ["RefBook"]

#: Slots allocated up front; the arrays double when full.
MIN_CAPACITY = 16
#: Typecode of both arrays (C ``int``; ``_refbook_c.pxd`` declares them ``int[::1]``).
TYPECODE = "i"
#: Fields of a resource record: reference count (-1: free slot), first and last dependency
#: (reference slots, -1: none; a free slot's HEAD is the next free slot).
RES_FIELDS, COUNT, HEAD, TAIL = 3, 0, 1, 2
#: Fields of a reference record: resource counted (-1: free slot), holder (resource slot, -1:
#: none), previous and next reference on the holder's list (a free slot's NEXT is the next
#: free slot).
REF_FIELDS, RES, HOLDER, PREV, NEXT = 4, 0, 1, 2, 3


def _filled(n: int) -> array[int]:
    """An array of ``n`` fields, all ``-1``."""
    return array(TYPECODE, [-1]) * n


class RefBook:
    """Reference counts and dependency lists of resources, by integer slot.

    A resource record holds the number of live references to the resource (``-1`` marks a
    free slot) and the first and last reference slot of its dependency list. A reference
    record holds the resource it counts (``-1`` marks a free slot), its holder (the resource
    whose dependency list it is on, ``-1`` for none) and its neighbours on that list. Free
    slots are chained through HEAD (resources) and NEXT (references).

    Not thread-safe: the registrar calls it with its lock held.
    """

    def __init__(self) -> None:
        self._rcap = MIN_CAPACITY
        self._rused = 0  # resource slots ever handed out (the rest are untouched)
        self._rfree = -1  # first free resource slot, or -1
        self._nres = 0
        self._rs: array[int] = _filled(MIN_CAPACITY * RES_FIELDS)
        self._fcap = MIN_CAPACITY
        self._fused = 0
        self._ffree = -1
        self._nref = 0
        self._fs: array[int] = _filled(MIN_CAPACITY * REF_FIELDS)

    # ------------------------------------------------------------------------------ resources

    def new_resource(self) -> int:
        """Allocate a resource slot with no references and no dependencies.

        Returns:
            The slot (the most recently freed one, if any).
        """
        res = self._rfree
        if res >= 0:
            self._rfree = self._rs[res * RES_FIELDS + HEAD]
        else:
            res = self._rused
            if res == self._rcap:
                self._grow_resources()
            self._rused = res + 1
        i = res * RES_FIELDS
        self._rs[i + COUNT] = 0
        self._rs[i + HEAD] = -1
        self._rs[i + TAIL] = -1
        self._nres += 1
        return res

    def free_resource(self, res: int) -> None:
        """Free a resource slot that has no references and holds no dependencies.

        Args:
            res: A live resource slot.

        Returns:
            None.

        Raises:
            KeyError: ``res`` is not a live resource slot.
            ValueError: It still has references, or still holds dependencies (release or
                :meth:`detach` them first).
        """
        count = self._live_res(res)
        i = res * RES_FIELDS
        if count:
            raise ValueError(f"resource slot {res} still has {count} reference(s)")
        if self._rs[i + HEAD] >= 0:
            raise ValueError(f"resource slot {res} still holds dependencies")
        self._rs[i + COUNT] = -1
        self._rs[i + HEAD] = self._rfree
        self._rfree = res
        self._nres -= 1

    def count(self, res: int) -> int:
        """The number of live references to a resource.

        Args:
            res: A live resource slot.

        Returns:
            The count (0 or more).

        Raises:
            KeyError: ``res`` is not a live resource slot.
        """
        return self._live_res(res)

    def dependencies(self, res: int) -> list[int]:
        """The reference slots a resource holds as dependencies.

        Args:
            res: A live resource slot.

        Returns:
            Reference slots in acquisition order (release them in reverse).

        Raises:
            KeyError: ``res`` is not a live resource slot.
        """
        self._live_res(res)
        out: list[int] = []
        ref = self._rs[res * RES_FIELDS + HEAD]
        while ref >= 0:
            out.append(ref)
            ref = self._fs[ref * REF_FIELDS + NEXT]
        return out

    def live_resources(self) -> int:
        """How many resource slots are allocated.

        Returns:
            The number of live resource slots.
        """
        return self._nres

    # ----------------------------------------------------------------------------- references

    def add_ref(self, res: int, holder: int) -> int:
        """Add a reference to a resource, as a dependency of ``holder`` or for a consumer.

        Args:
            res: The live resource slot the reference counts.
            holder: The live resource slot that holds the reference as a dependency (appended
                to its list), or ``-1`` for a consumer's reference. The book does not look for
                cycles; ``holder`` may even be ``res``.

        Returns:
            The new reference slot (the most recently freed one, if any).

        Raises:
            KeyError: ``res``, or ``holder`` if not ``-1``, is not a live resource slot.
        """
        self._live_res(res)
        if holder != -1:
            self._live_res(holder)
        ref = self._ffree
        if ref >= 0:
            self._ffree = self._fs[ref * REF_FIELDS + NEXT]
        else:
            ref = self._fused
            if ref == self._fcap:
                self._grow_refs()
            self._fused = ref + 1
        i = ref * REF_FIELDS
        self._fs[i + RES] = res
        self._fs[i + HOLDER] = holder
        self._fs[i + NEXT] = -1
        if holder == -1:
            self._fs[i + PREV] = -1
        else:
            h = holder * RES_FIELDS
            last = self._rs[h + TAIL]
            self._fs[i + PREV] = last
            if last >= 0:
                self._fs[last * REF_FIELDS + NEXT] = ref
            else:
                self._rs[h + HEAD] = ref
            self._rs[h + TAIL] = ref
        self._rs[res * RES_FIELDS + COUNT] += 1
        self._nref += 1
        return ref

    def release(self, ref: int) -> int:
        """Remove a reference: unlink it from its holder's list and free its slot.

        Args:
            ref: A live reference slot.

        Returns:
            The number of references its resource has left (0: the resource may be unloaded).

        Raises:
            KeyError: ``ref`` is not a live reference slot.
        """
        res = self._live_ref(ref)
        self._unlink(ref)
        i = ref * REF_FIELDS
        self._fs[i + RES] = -1
        self._fs[i + NEXT] = self._ffree
        self._ffree = ref
        self._nref -= 1
        r = res * RES_FIELDS + COUNT
        left = self._rs[r] - 1
        self._rs[r] = left
        return left

    def detach(self, ref: int) -> None:
        """Take a reference off its holder's dependency list; it stays counted (holder -1).

        Args:
            ref: A live reference slot.

        Returns:
            None.

        Raises:
            KeyError: ``ref`` is not a live reference slot.
        """
        self._live_ref(ref)
        self._unlink(ref)

    def resource_of(self, ref: int) -> int:
        """The resource a reference counts.

        Args:
            ref: A live reference slot.

        Returns:
            The resource slot.

        Raises:
            KeyError: ``ref`` is not a live reference slot.
        """
        return self._live_ref(ref)

    def holder_of(self, ref: int) -> int:
        """The resource that holds a reference as a dependency.

        Args:
            ref: A live reference slot.

        Returns:
            The holder's resource slot, or ``-1`` (a consumer's reference, or detached).

        Raises:
            KeyError: ``ref`` is not a live reference slot.
        """
        self._live_ref(ref)
        return self._fs[ref * REF_FIELDS + HOLDER]

    def live_refs(self) -> int:
        """How many reference slots are allocated.

        Returns:
            The number of live reference slots.
        """
        return self._nref

    # -------------------------------------------------------------------------------- helpers

    def _live_res(self, res: int) -> int:
        """``res``'s reference count; KeyError unless it is a live resource slot."""
        if res < 0 or res >= self._rused or self._rs[res * RES_FIELDS + COUNT] < 0:
            raise KeyError(f"no live resource slot {res}")
        return self._rs[res * RES_FIELDS + COUNT]

    def _live_ref(self, ref: int) -> int:
        """``ref``'s resource slot; KeyError unless it is a live reference slot."""
        if ref < 0 or ref >= self._fused or self._fs[ref * REF_FIELDS + RES] < 0:
            raise KeyError(f"no live reference slot {ref}")
        return self._fs[ref * REF_FIELDS + RES]

    def _unlink(self, ref: int) -> None:
        """Take a live reference off its holder's list (if any); its holder becomes -1."""
        i = ref * REF_FIELDS
        holder = self._fs[i + HOLDER]
        if holder >= 0:
            h = holder * RES_FIELDS
            before = self._fs[i + PREV]
            after = self._fs[i + NEXT]
            if before >= 0:
                self._fs[before * REF_FIELDS + NEXT] = after
            else:
                self._rs[h + HEAD] = after
            if after >= 0:
                self._fs[after * REF_FIELDS + PREV] = before
            else:
                self._rs[h + TAIL] = before
            self._fs[i + HOLDER] = -1
            self._fs[i + PREV] = -1
            self._fs[i + NEXT] = -1

    def _grow_resources(self) -> None:
        """Double the resource array (a new array, contents copied, attribute re-assigned)."""
        n = self._rcap * RES_FIELDS
        rs = _filled(2 * n)
        rs[:n] = self._rs[:n]
        self._rs = rs
        self._rcap *= 2

    def _grow_refs(self) -> None:
        """Double the reference array (a new array, contents copied, attribute re-assigned)."""
        n = self._fcap * REF_FIELDS
        fs = _filled(2 * n)
        fs[:n] = self._fs[:n]
        self._fs = fs
        self._fcap *= 2

# C declarations for the compiled build of _evolution_py.py (docs/development.md §7); the .py file is
# the one source of behaviour, this file only adds types.
cimport cython

cdef class Evolution:
    cdef public int n_nodes
    cdef int[::1] edge_start
    cdef int[::1] edge_child
    cdef int[::1] edge_slot
    cdef signed char[::1] edge_response
    cdef int[::1] slot_start
    cdef signed char[::1] slot_required
    cdef signed char[::1] received
    cdef int[::1] missing
    cdef public int exit_node
    cdef int wave
    cdef int[::1] marks
    cdef int[::1] queue

    @cython.locals(wave=int, head=int, tail=int, node=int, e=int, end=int, child=int, slot=int,
                   response=int, ready=int, i=int, n_results=int, shift=int, bypass=int,
                   loop=int, ignore=int, exit_node=int)
    cpdef list propagate(self, int parent, int result)

    @cython.locals(e=int, child=int, slot=int, n_results=int, run=int)
    cpdef int advance(self, int parent, int result) except? -2

    @cython.locals(new=Evolution, n=int, n_slots=int, c=int, s=int, end=int)
    cpdef Evolution fresh(self)

    cpdef int missing_parents(self, int node)

    @cython.locals(s=int, end=int)
    cpdef bint received_any(self, int node)

@cython.locals(idle=long, error=long, i=int, base=int, n_states=int, idle_true=int,
               idle_false=int, in_error=int)
cpdef int default_evolution(const signed char[:] rows, int n_rows) except? -1

# C declarations for the compiled build of _node_py.py (STYLE.md 3.9); the .py file is the one
# source of behaviour, this file only adds types: the records become extension types whose
# fields the chain loop reads and writes directly.
cimport cython

from temoto.core._fast._evolution_c cimport Evolution

cdef class ControlCore:
    cdef public object acquired
    cdef public object broken
    cdef public object clock
    cdef public object condition
    cdef public object logged
    cdef public object paused
    cdef public object stop

cdef class NodeCore(ControlCore):
    cdef public object child_run
    cdef public object cls
    cdef public object data
    cdef public object error
    cdef public object fresh_instance
    cdef public object gen
    cdef public object held
    cdef public object idx
    cdef public object inline
    cdef public object inputs
    cdef public object instance
    cdef public object kind
    cdef public object last_outputs
    cdef public object log
    cdef public object name
    cdef public object native
    cdef public object outputs
    cdef public object plan
    cdef public object remote_cancel
    cdef public object required_inputs
    cdef public object restart
    cdef public object run
    cdef public object spontaneous
    cdef public object state
    cdef public object stop_timer
    cdef public object umrf

@cython.locals(child=NodeCore, evolution=Evolution, step=int, edge=int, code=int, shift=int,
               run_ready=int, run_waits=int)
cpdef run_chain(engine, NodeCore node, gen, instance, values, fx, list todo, tuple k)

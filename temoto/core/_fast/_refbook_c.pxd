# C declarations for the compiled build of _refbook_py.py (extension temoto.core._fast._refbook_c).
# docs/development.md §7: the .py is the only source; this file only adds types. Keep the method list and
# signatures in step with RefBook in _refbook_py.py.
#
# Cython picks this file up by the *extension's* name (_refbook_c), not the source's; a
# _refbook_py.pxd would be ignored (checked with Cython 3.3.1). Do not mark the class
# @cython.final: with `long long ... except -1` methods Cython 3.3.1 then emits the invalid C
# constant `-1LLLL`. Slot arguments are `long long`, stored as C `int` (32-bit records).

cimport cython

cdef Py_ssize_t RES_FIELDS, COUNT, HEAD, TAIL
cdef Py_ssize_t REF_FIELDS, RES, HOLDER, PREV, NEXT

cdef object _filled(Py_ssize_t n)


cdef class RefBook:
    cdef Py_ssize_t _rcap, _rused, _nres, _fcap, _fused, _nref
    cdef long long _rfree, _ffree
    cdef int[::1] _rs, _fs

    @cython.locals(res="long long", i=Py_ssize_t)
    cpdef long long new_resource(self) except -1
    @cython.locals(count="long long", i=Py_ssize_t)
    cpdef free_resource(self, long long res)
    cpdef long long count(self, long long res) except -1
    @cython.locals(out=list, ref="long long")
    cpdef list dependencies(self, long long res)
    cpdef Py_ssize_t live_resources(self)

    @cython.locals(ref="long long", i=Py_ssize_t, h=Py_ssize_t, last="long long")
    cpdef long long add_ref(self, long long res, long long holder) except -1
    @cython.locals(res="long long", i=Py_ssize_t, r=Py_ssize_t, left="long long")
    cpdef long long release(self, long long ref) except -1
    cpdef detach(self, long long ref)
    cpdef long long resource_of(self, long long ref) except -1
    cpdef long long holder_of(self, long long ref) except -2  # -1 is a valid answer
    cpdef Py_ssize_t live_refs(self)

    cdef long long _live_res(self, long long res) except -1
    cdef long long _live_ref(self, long long ref) except -1
    @cython.locals(i=Py_ssize_t, h=Py_ssize_t, holder="long long", before="long long",
                   after="long long")
    cdef int _unlink(self, long long ref) except -1
    @cython.locals(n=Py_ssize_t, rs="int[::1]")
    cdef int _grow_resources(self) except -1
    @cython.locals(n=Py_ssize_t, fs="int[::1]")
    cdef int _grow_refs(self) except -1

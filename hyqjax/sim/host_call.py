"""A Python function called from a jitted CPU program as an XLA FFI target, so that the program can be cached.

``jax.experimental.io_callback`` (and ``pure_callback``) bake a pointer to their Python callable into the
compiled program, and JAX never writes such a program to its persistent compilation cache: every new process
would compile it again. A typed XLA FFI custom call names its target by a string instead (the lowered program
holds ``stablehlo.custom_call @name``, no pointer), so a program calling one is cached and loaded like any other,
as long as the target is registered in the loading process before the program runs.

:func:`register` makes a Python function such a target on the CPU: a ``ctypes`` function pointer that reads XLA's
call frame (the structures of ``xla/ffi/api/c_api.h``, FFI API version 0.1: the buffers of the arguments and
results, each ``dtype, data, rank, dims``) and hands the function NumPy views of the argument and result buffers;
the function writes its results into the result views in place. :func:`call` calls it from JAX
(``jax.ffi.ffi_call`` with ``has_side_effect=True``, so it is never removed or merged).

An exception in the function cannot cross the C boundary: the results are filled with NaN (a run that reads
them diverges at once instead of continuing on stale numbers) and the exception is kept; :func:`raise_pending`
raises it in the caller once the program has returned.
"""
from __future__ import annotations

import ctypes
import threading
from typing import Callable

import numpy as np

#: XLA_FFI_DataType codes (``xla_data.proto``'s PrimitiveType) of the buffers a target may see.
_DTYPES = {1: np.bool_, 4: np.int32, 5: np.int64, 11: np.float32, 12: np.float64}
_EXTENSION_METADATA = 1  # XLA_FFI_Extension_Metadata
_STAGE_EXECUTE = 3  # XLA_FFI_ExecutionStage_EXECUTE
#: The FFI API version the handler reads (the call frame layout below): XLA accepts 0.1 and later minors.
_API_VERSION = (0, 1)


class _ExtensionBase(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("type", ctypes.c_int), ("next", ctypes.c_void_p)]


class _ApiVersion(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("major_version", ctypes.c_int), ("minor_version", ctypes.c_int)]


class _Metadata(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("api_version", _ApiVersion), ("traits", ctypes.c_uint32),
                ("state_type_id", ctypes.c_int64)]


class _MetadataExtension(ctypes.Structure):
    _fields_ = [("extension_base", _ExtensionBase), ("metadata", ctypes.POINTER(_Metadata))]


class _Buffer(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("dtype", ctypes.c_int),
                ("data", ctypes.c_void_p), ("rank", ctypes.c_int64), ("dims", ctypes.POINTER(ctypes.c_int64))]


class _Buffers(ctypes.Structure):  # XLA_FFI_Args and XLA_FFI_Rets (the same layout)
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("size", ctypes.c_int64),
                ("types", ctypes.c_void_p), ("buffers", ctypes.POINTER(ctypes.c_void_p))]


class _Attrs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("size", ctypes.c_int64),
                ("types", ctypes.c_void_p), ("names", ctypes.c_void_p), ("attrs", ctypes.c_void_p)]


class _CallFrame(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)),
                ("api", ctypes.c_void_p), ("ctx", ctypes.c_void_p), ("stage", ctypes.c_int), ("args", _Buffers),
                ("rets", _Buffers), ("attrs", _Attrs), ("future", ctypes.c_void_p)]


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_CallFrame))
_lock = threading.Lock()
_TARGETS: dict[str, tuple[Callable, object]] = {}  # name -> (function, ctypes handler kept alive)
_ERRORS: dict[str, BaseException] = {}


def _view(address: int) -> np.ndarray:
    """A NumPy view of one XLA_FFI_Buffer (valid while the call lasts)."""
    b = _Buffer.from_address(address)
    dtype = np.dtype(_DTYPES[b.dtype])
    shape = tuple(b.dims[i] for i in range(b.rank))
    n = int(np.prod(shape, dtype=np.int64)) if shape else 1
    raw = (ctypes.c_char * (n * dtype.itemsize)).from_address(b.data)
    return np.frombuffer(raw, dtype).reshape(shape)


def _make_handler(name: str, fn: Callable):
    def handler(frame_ptr):
        frame = frame_ptr.contents
        if frame.extension_start:  # XLA asks for the handler's metadata when it is registered
            if frame.extension_start.contents.type == _EXTENSION_METADATA:
                meta = ctypes.cast(frame.extension_start, ctypes.POINTER(_MetadataExtension)).contents.metadata.contents
                meta.api_version.major_version, meta.api_version.minor_version = _API_VERSION
                meta.traits = 0
            return None
        if frame.stage != _STAGE_EXECUTE:
            return None
        outs = [_view(frame.rets.buffers[i]) for i in range(frame.rets.size)]
        try:
            fn([_view(frame.args.buffers[i]) for i in range(frame.args.size)], outs)
        except BaseException as e:  # noqa: BLE001  (kept for raise_pending: it cannot cross into XLA)
            _ERRORS.setdefault(name, e)
            for o in outs:
                if np.issubdtype(o.dtype, np.floating):
                    o[...] = np.nan
        return None

    return _HANDLER(handler)


def register(name: str, fn: Callable[[list[np.ndarray], list[np.ndarray]], None]) -> None:
    """Make ``fn(args, results)`` the CPU FFI target ``name`` of this process (once; registering the same name
    again replaces the Python function XLA's handler calls). ``args`` and ``results`` are NumPy views of the
    call's buffers; ``fn`` writes every result in place."""
    import jax

    with _lock:
        if name in _TARGETS:
            _TARGETS[name] = (fn, _TARGETS[name][1])
            return
        cfunc = _make_handler(name, lambda a, r: _TARGETS[name][0](a, r))
        _TARGETS[name] = (fn, cfunc)
        new_capsule = ctypes.pythonapi.PyCapsule_New
        new_capsule.restype = ctypes.py_object
        new_capsule.argtypes = (ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p)
        capsule = new_capsule(ctypes.cast(cfunc, ctypes.c_void_p).value, b"xla._CUSTOM_CALL_TARGET", None)
        jax.ffi.register_ffi_target(name, capsule, platform="cpu")


def call(name: str, result_shape_dtypes, *args):
    """Call target ``name`` (registered with :func:`register`) from JAX; never removed or merged by XLA."""
    import jax

    return jax.ffi.ffi_call(name, result_shape_dtypes, has_side_effect=True)(*args)


def raise_pending(name: str) -> None:
    """Raise (once) the first exception target ``name`` raised since the last check."""
    err = _ERRORS.pop(name, None)
    if err is not None:
        raise err


def discard_pending(name: str) -> None:
    """Forget an exception of target ``name`` left unraised (by a call that failed for another reason)."""
    _ERRORS.pop(name, None)

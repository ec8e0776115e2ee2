"""One definition per parameter: range, unit, scale and orderings declared once, as dataclass metadata.

A parameter class is a frozen dataclass made with :func:`params_dataclass`; each field is declared
with :func:`param_field` (range ``[lo, hi]`` with open or closed ends, unit, scale, allowed trailing
shapes, a one-line description), and cross-field orderings (``d_st_min < d_st_max``) are
:class:`Ordering` entries given to the decorator. From that one declaration:

* construction and :meth:`replace` validate every *concrete* value (Python numbers, NumPy arrays,
  concrete ``jax.Array`` s; every element of a batched leaf) and raise :class:`ParameterError`, one
  line naming the parameter and its allowed range; traced or abstract values (inside ``jit``,
  ``vmap``, ``grad``) are skipped, so constructing parameters inside a transformation works;
* the class is a JAX PyTree (every non-static field a leaf, so ``grad`` and ``vmap`` reach it);
  unflattening bypasses ``__init__``: ``jax.tree.map`` and transformations never validate;
* :func:`param_ranges` and :func:`param_orderings` expose the declaration to sweep axes, command-line
  help and a tuner's reparameterisation (:meth:`ParamSpec.constrain` maps an unconstrained real to
  the range and :meth:`ParamSpec.unconstrain` back);
* :func:`batch_params` broadcasts a parameter set to a batch of ``n`` with per-instance overrides,
  also of nested parameter classes, and validates the batch.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Ordering",
    "ParamSpec",
    "ParameterError",
    "batch_params",
    "check_params",
    "is_concrete",
    "param_field",
    "param_orderings",
    "param_ranges",
    "params_dataclass",
]


class ParameterError(ValueError):
    """A parameter is outside its allowed range; the message is one line naming both.

    Attributes: ``owner`` (class name), ``param`` (field name), ``allowed`` (the range or rule as
    text), ``value`` (the offending value, first offending element of a batch).
    """

    def __init__(self, owner: str, param: str, value: Any, allowed: str, problem: str = "out of range"):
        self.owner, self.param, self.value, self.allowed = owner, param, value, allowed
        super().__init__(f"{owner}.{param}={_fmt(value)} {problem}: must be {allowed}")


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    return repr(v) if not isinstance(v, np.ndarray) else np.array2string(v, precision=6)


def _num(x: float) -> str:
    return "inf" if x == math.inf else ("-inf" if x == -math.inf else f"{x:g}")


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """The declaration of one parameter (see :func:`param_field`)."""

    name: str
    default: Any
    lo: float
    hi: float
    unit: str
    doc: str
    lo_open: bool
    hi_open: bool
    shapes: tuple[tuple[int, ...], ...]
    scale: str
    static: bool

    @property
    def range_text(self) -> str:
        """``"in (0, 1e+05] N m s/rad"``: the allowed range as written in error messages and help."""
        left, right = ("(" if self.lo_open else "["), (")" if self.hi_open else "]")
        unit = f" {self.unit}" if self.unit else ""
        return f"in {left}{_num(self.lo)}, {_num(self.hi)}{right}{unit}"

    def help(self) -> str:
        """One line for command-line help: description, range, default."""
        d = self.default
        d = d.tolist() if isinstance(d, np.ndarray) else d
        return f"{self.doc} ({self.range_text}; default {d})"

    def in_range(self, a: np.ndarray) -> np.ndarray:
        """Element-wise: finite and inside ``[lo, hi]`` (ends open as declared)."""
        a = np.asarray(a, np.float64)
        ok = np.isfinite(a)
        ok &= (a > self.lo) if self.lo_open else (a >= self.lo)
        ok &= (a < self.hi) if self.hi_open else (a <= self.hi)
        return ok

    def check(self, value, owner: str = "") -> None:
        """Raise :class:`ParameterError` unless every element of ``value`` is in range and its trailing
        shape is one of :attr:`shapes` (leading batch dimensions are allowed)."""
        a = _as_float_array(value, owner, self.name, self.range_text)
        if np.asarray(value).dtype == np.float32:  # float32(0.3) = 0.30000001 is the declared end 0.3 itself
            f32 = np.asarray(value)
            a = np.where(f32 == np.float32(self.lo), self.lo, np.where(f32 == np.float32(self.hi), self.hi, a))
        ok = self.in_range(a)
        if not ok.all():
            bad = a[~ok][0] if a.ndim else a
            raise ParameterError(owner, self.name, float(bad), self.range_text)
        if not any(a.shape[a.ndim - len(s):] == s for s in self.shapes if len(s) <= a.ndim):
            raise ParameterError(owner, self.name, f"array of shape {a.shape}",
                                 f"of shape {' or '.join(map(str, self.shapes))} (leading batch axes allowed)",
                                 problem="has a wrong shape")

    # -------- reparameterisation (unconstrained real <-> range), traceable --------
    def constrain(self, theta):
        """Map an unconstrained real (array) into the range: ``lo + (hi - lo) sigmoid(theta)`` (or in
        ``log`` for ``scale="log"``), ``lo + exp(theta)`` if ``hi`` is infinite. Traceable."""
        if math.isinf(self.hi):
            return self.lo + jnp.exp(theta)
        if self.scale == "log":
            a, b = math.log(self.lo), math.log(self.hi)
            return jnp.exp(a + (b - a) * jax.nn.sigmoid(theta))
        return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(theta)

    def unconstrain(self, value, eps: float = 1e-6):
        """Inverse of :meth:`constrain` (values at a closed end are moved ``eps`` inside)."""
        v = np.asarray(value, np.float64)
        if math.isinf(self.hi):
            return np.log(np.maximum(v - self.lo, eps))
        if self.scale == "log":
            a, b = math.log(self.lo), math.log(self.hi)
            u = (np.log(v) - a) / (b - a)
        else:
            u = (v - self.lo) / (self.hi - self.lo)
        u = np.clip(u, eps, 1.0 - eps)
        return np.log(u / (1.0 - u))


@dataclasses.dataclass(frozen=True)
class Ordering:
    """``lhs OP rhs`` element-wise between two fields of one class (``op`` is ``"<"`` or ``"<="``)."""

    lhs: str
    op: str
    rhs: str
    why: str = ""

    def holds(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        try:
            return (a < b) if self.op == "<" else (a <= b)
        except ValueError:  # batch shapes that do not broadcast: compare the extremes
            return np.asarray((a.max() < b.min()) if self.op == "<" else (a.max() <= b.min()))


def param_field(default, lo: float = -math.inf, hi: float = math.inf, unit: str = "", doc: str = "", *,
                lo_open: bool = False, hi_open: bool = False, shapes=((),), scale: str = "linear",
                static: bool = False):
    """A dataclass field carrying its :class:`ParamSpec` (range ``lo..hi``, ``unit``, ``doc``).

    ``shapes``: allowed trailing shapes of the value (e.g. ``((), (3,))`` for a scalar or a diagonal);
    leading batch axes are always allowed. ``scale`` (``"linear"`` or ``"log"``) is how sweeps and
    tuners should spread the range. ``static=True`` makes the field PyTree metadata (not a leaf).
    A ``default`` that is a tuple or list is stored as a NumPy array.
    """
    if scale not in ("linear", "log") or (scale == "log" and not lo > 0):
        raise ValueError(f"param_field scale must be 'linear' or 'log' (log needs lo > 0), got {scale!r}")
    spec = ParamSpec("", default, float(lo), float(hi), unit, doc, lo_open, hi_open,
                     tuple(tuple(s) for s in shapes), scale, static)
    if isinstance(default, (tuple, list)):
        arr = np.asarray(default, np.float32)
        return dataclasses.field(default_factory=lambda: arr.copy(), metadata={"param": spec})
    # ``static`` in the field's metadata is what jax.tree_util.register_dataclass reads to make it PyTree metadata.
    return dataclasses.field(default=default, metadata={"param": spec, **({"static": True} if static else {})})


def is_concrete(x) -> bool:
    """False for a tracer or an abstract shape (``jax.ShapeDtypeStruct``), True otherwise (the value is
    checked now; anything that is not a number then fails its check)."""
    return not isinstance(x, (jax.core.Tracer, jax.ShapeDtypeStruct))


def _as_float_array(value, owner, name, allowed) -> np.ndarray:
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError) as e:
        raise ParameterError(owner, name, value, f"a number or an array of numbers {allowed}") from e


def param_ranges(cls_or_obj) -> dict[str, ParamSpec]:
    """``{field name: ParamSpec}`` of a parameter class (or instance), in declaration order."""
    cls = cls_or_obj if isinstance(cls_or_obj, type) else type(cls_or_obj)
    out = {}
    for f in dataclasses.fields(cls):
        spec = f.metadata.get("param")
        if spec is not None:
            out[f.name] = dataclasses.replace(spec, name=f.name, default=_default(f))
    return out


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def param_orderings(cls_or_obj) -> tuple[Ordering, ...]:
    """The :class:`Ordering` s declared for a parameter class (or instance)."""
    cls = cls_or_obj if isinstance(cls_or_obj, type) else type(cls_or_obj)
    return tuple(getattr(cls, "__param_orderings__", ()))


def check_params(obj) -> None:
    """Validate every concrete field of a parameter object against its declaration (see module doc).

    Ranges are checked element-wise (batched leaves included), then the orderings between fields whose
    values are both concrete. Traced/abstract values are skipped. Raises :class:`ParameterError`.
    """
    owner = type(obj).__name__
    specs = param_ranges(obj)
    vals: dict[str, np.ndarray] = {}
    for name, spec in specs.items():
        v = getattr(obj, name)
        if spec.static or not is_concrete(v):
            continue
        spec.check(v, owner)
        vals[name] = np.asarray(v, np.float64)
    for o in param_orderings(obj):
        if o.lhs in vals and o.rhs in vals:
            a, b = vals[o.lhs], vals[o.rhs]
            ok = np.asarray(o.holds(a, b))
            if not ok.all():
                ab = np.broadcast_arrays(a, b) if a.shape == b.shape or a.ndim == 0 or b.ndim == 0 else (a, b)
                i = np.argmin(ok.reshape(-1)) if ok.ndim else 0
                va = float(ab[0].reshape(-1)[i]) if ab[0].size == ok.size else float(a.max())
                vb = float(ab[1].reshape(-1)[i]) if ab[1].size == ok.size else float(b.min())
                why = f" ({o.why})" if o.why else ""
                raise ParameterError(owner, o.lhs, va, f"{o.op} {o.rhs}={vb:.6g}{why}")


def params_dataclass(cls=None, *, orderings: tuple[Ordering, ...] = ()):
    """Class decorator: frozen dataclass + JAX PyTree + validation at construction and in ``replace``.

    ``__post_init__`` runs :func:`check_params` (after the class's own ``__post_init__`` if any), so
    ``Cls(...)``, ``dataclasses.replace`` and ``.replace(...)`` all validate concrete values. The class
    may define ``validate(self, ...)`` for further checks (it must call :func:`check_params` and return
    ``self``); otherwise ``validate`` is :func:`check_params` returning ``self``.
    Fields of a nested parameter class are validated by that class when it is built.
    """

    def wrap(c):
        c.__param_orderings__ = tuple(orderings)
        if "validate" not in c.__dict__:
            def validate(self):
                """Check every concrete field against its declared range and the orderings; return ``self``."""
                check_params(self)
                return self
            c.validate = validate
        if "replace" not in c.__dict__:
            def replace(self, **kwargs):
                """``dataclasses.replace`` that validates the result (unknown names are refused)."""
                names = {f.name for f in dataclasses.fields(self)}
                unknown = sorted(set(kwargs) - names)
                if unknown:
                    raise ParameterError(type(self).__name__, unknown[0], kwargs[unknown[0]],
                                         f"one of the fields {sorted(names)}")
                return dataclasses.replace(self, **kwargs)
            c.replace = replace
        user_post = c.__dict__.get("__post_init__")

        def __post_init__(self):
            for f in dataclasses.fields(self):  # tuple/list leaves become arrays (a tuple would be a subtree)
                v = getattr(self, f.name)
                if "param" in f.metadata and isinstance(v, (tuple, list)):
                    object.__setattr__(self, f.name, np.asarray(v, np.float32))
            if user_post is not None:
                user_post(self)
            check_params(self)

        c.__post_init__ = __post_init__
        c = dataclasses.dataclass(frozen=True)(c)
        fields = dataclasses.fields(c)
        data = tuple(f.name for f in fields if not f.metadata.get("param", _NOSPEC).static)
        meta = tuple(f.name for f in fields if f.metadata.get("param", _NOSPEC).static)
        _register(c, data, meta)
        return c

    return wrap if cls is None else wrap(cls)


_NOSPEC = ParamSpec("", None, -math.inf, math.inf, "", "", False, False, ((),), "linear", False)


def _register(c, data: tuple[str, ...], meta: tuple[str, ...]):
    keys = tuple(jax.tree_util.GetAttrKey(n) for n in data)

    def flatten_with_keys(x):
        return tuple(zip(keys, (getattr(x, n) for n in data))), tuple(getattr(x, n) for n in meta)

    def flatten(x):
        return tuple(getattr(x, n) for n in data), tuple(getattr(x, n) for n in meta)

    def unflatten(aux, children):  # no __init__: transformations rebuild without validating
        obj = object.__new__(c)
        for n, v in zip(meta, aux):
            object.__setattr__(obj, n, v)
        for n, v in zip(data, children):
            object.__setattr__(obj, n, v)
        return obj

    jax.tree_util.register_pytree_with_keys(c, flatten_with_keys, unflatten, flatten)


def batch_params(base, n: int, **overrides):
    """``base`` broadcast to a batch of ``n`` (leading axis on every leaf), with per-instance overrides.

    An override is a value broadcastable to ``(n,) + field shape`` (a scalar, or one value per
    instance); for a field that is itself a parameter class give a dict, e.g.
    ``batch_params(crawl_params, n, forward_velocity=v, reflex=dict(k_base=kb))``, or a dotted key
    ``**{"reflex.k_base": kb}``. The result is validated (every element). Leaves become ``jnp`` arrays
    keeping their dtype (Python floats become float32).
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ParameterError("batch_params", "n", n, "an integer >= 1")
    nested: dict[str, dict] = {}
    flat: dict[str, Any] = {}
    for k, v in overrides.items():
        head, _, rest = k.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = v
        elif isinstance(v, dict):
            nested.setdefault(head, {}).update(v)
        else:
            flat[k] = v
    return _batch(base, int(n), flat, nested)


def _batch(base, n, flat, nested):
    owner = type(base).__name__
    names = {f.name for f in dataclasses.fields(base)}
    for k in list(flat) + list(nested):
        if k not in names:
            raise ParameterError(owner, k, flat.get(k, nested.get(k)), f"one of the fields {sorted(names)}")
    static = {f.name for f in dataclasses.fields(base) if f.metadata.get("param", _NOSPEC).static}
    kw = {}
    for f in dataclasses.fields(base):
        v = getattr(base, f.name)
        if f.name in static:
            continue
        if f.name in nested:
            kw[f.name] = _batch(v, n, {k: x for k, x in nested[f.name].items() if "." not in k},
                                {k.split(".", 1)[0]: {k.split(".", 1)[1]: x}
                                 for k, x in nested[f.name].items() if "." in k})
        elif dataclasses.is_dataclass(v):
            kw[f.name] = _batch(v, n, {}, {})
        else:
            val = flat.get(f.name, v)
            shape = (n,) + tuple(jnp.shape(v))
            # NumPy for concrete values: the batch is validated before anything is compiled or sent to a device.
            xp = jnp if isinstance(val, jax.core.Tracer) or isinstance(v, jax.core.Tracer) else np
            try:
                x = xp.asarray(val).astype(jnp.result_type(v))
            except (TypeError, ValueError) as e:
                raise ParameterError(owner, f.name, val, f"numbers of dtype {jnp.result_type(v)}") from e
            try:
                kw[f.name] = xp.broadcast_to(x, shape)
            except ValueError as e:
                raise ParameterError(owner, f.name, f"array of shape {x.shape}", f"broadcastable to {shape}") from e
    out = dataclasses.replace(base, **kw)  # validated here (every element)
    return jax.tree.map(lambda a: jnp.asarray(a) if isinstance(a, np.ndarray) else a, out)


def field_doc_table(cls) -> str:
    """A plain-text table of a parameter class's fields (name, range, default, description)."""
    rows = [f"{s.name:12s} {s.range_text:28s} default {s.default!s:10s} {s.doc}" for s in param_ranges(cls).values()]
    return "\n".join(rows)


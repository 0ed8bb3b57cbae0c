"""Field tables: a message's fields declared once; validation and (de)serialisation derived.

A message class (see protocol/messages.py) is a dataclass declared with `@message` whose
fields are declared with `wire(kind, ...)`: the field's `Kind` (its wire type, validation and
codec), wire name, unit, and whether it is required. `@message` turns those declarations into
the class's field table `FIELDS` (a `WireField` per row: what docs/reference/protocol.md lists), and
`check_fields` / `fields_to_wire` / `fields_from_wire` do the checks at construction, the
encoding and the validating decoding from that table alone.

Every rejection is `ProtocolError("bad_request", "<field>: ...")` naming the field, the value
received and the allowed range. This module knows types, not the protocol's messages.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import numpy as np

if sys.version_info >= (3, 11):
    from typing import dataclass_transform
else:  # Python 3.10 (ROS 2 Humble)
    from typing_extensions import dataclass_transform

from protocol.arrays import IMAGE_ENCODINGS, decode_image, decode_nd, encode_image, encode_nd
from protocol.errors import ProtocolError

MISSING_VALUE: Any = object()
"""Returned by `Derived.derive` for "use the default"."""

_INT_MIN = -(2**63)
_INT_MAX = 2**64 - 1


# ----------------------------------------------------------------------------------------------
# Small typed readers for wire values. Each raises ProtocolError("bad_request", "<field>: ...").
# ----------------------------------------------------------------------------------------------


def bad(what: str) -> ProtocolError:
    return ProtocolError("bad_request", what)


def short(value: Any) -> str:
    try:
        text = repr(value)
    except RecursionError:  # a hostile, deeply nested value (found by benchmarks/robustness/fuzz.py)
        text = f"<{type_name(value)} nested too deeply to show>"
    return text if len(text) <= 60 else text[:57] + "..."


def type_name(value: Any) -> str:
    return "bool" if isinstance(value, bool) else type(value).__name__


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_int(name: str, value: Any, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, np.integer):
        value = int(value)
    if not is_int(value):
        raise bad(f"{name}: expected an int, got {type_name(value)} {short(value)}")
    if not _INT_MIN <= value <= _INT_MAX:
        raise bad(f"{name}: {short(value)} does not fit in a 64-bit msgpack int")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        rng = f"{'' if lo is None else lo}..{'' if hi is None else hi}"
        raise bad(f"{name}: {value} out of range {rng}")
    return int(value)


def check_float(name: str, value: Any, *, finite: bool = True, lo: float | None = None) -> float:
    if isinstance(value, np.floating | np.integer):
        value = value.item()
    if not is_number(value):
        raise bad(f"{name}: expected a number, got {type_name(value)} {short(value)}")
    out = float(value)
    if finite and not math.isfinite(out):
        raise bad(f"{name}: must be finite, got {out}")
    if lo is not None and not out >= lo:
        raise bad(f"{name}: {out} out of range {lo}..")
    return out


def check_str(name: str, value: Any, *, max_chars: int, nonempty: bool = True) -> str:
    if not isinstance(value, str):
        raise bad(f"{name}: expected a string, got {type_name(value)} {short(value)}")
    if nonempty and not value:
        raise bad(f"{name}: must be a non-empty string")
    if len(value) > max_chars:
        raise bad(f"{name}: {len(value)} characters, at most {max_chars} allowed")
    return value


def check_str_map(name: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise bad(f"{name}: expected a map, got {type_name(value)}")
    for key in value:
        if not isinstance(key, str):
            raise bad(f"{name}: keys must be strings, got {type_name(key)} {short(key)}")
    return dict(value)


def check_array(
    name: str, value: Any, dtype: str, shape: tuple[int | None, ...], *, coerce: bool = False
) -> np.ndarray:
    """Check (or, with `coerce`, convert to) an ndarray of `dtype` and `shape` (None = any)."""
    if coerce:
        try:
            value = np.ascontiguousarray(value, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise bad(f"{name}: cannot convert to a {dtype} array: {exc}") from None
    if not isinstance(value, np.ndarray):
        raise bad(f"{name}: expected a numpy array, got {type_name(value)}")
    if value.dtype != np.dtype(dtype):
        raise bad(f"{name}: expected dtype {dtype}, got {value.dtype}")
    mismatch = value.ndim != len(shape) or any(
        w is not None and g != w for g, w in zip(value.shape, shape, strict=True)
    )
    if mismatch:
        want = "(" + ", ".join("*" if w is None else str(w) for w in shape) + ")"
        raise bad(f"{name}: expected shape {want}, got {value.shape}")
    return value


def wire_numbers(name: str, value: Any, count: int) -> np.ndarray:
    """A wire list of `count` numbers -> (count,) float64 (finiteness is checked by the caller)."""
    if not isinstance(value, list | tuple):
        raise bad(f"{name}: expected a list of {count} numbers, got {type_name(value)} {short(value)}")
    if len(value) != count:
        raise bad(f"{name}: expected {count} numbers, got {len(value)}")
    for i, x in enumerate(value):
        if not is_number(x):
            raise bad(f"{name}[{i}]: expected a number, got {type_name(x)} {short(x)}")
    return np.array([float(x) for x in value], dtype=np.float64)


def equal(a: Any, b: Any) -> bool:
    """Exact structural equality, arrays included (same dtype, shape and values; NaN == NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        if a.dtype != b.dtype or a.shape != b.shape:
            return False
        return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


# ----------------------------------------------------------------------------------------------
# Field kinds: the type of one field -- its docs type text, its validation and its codec
# ----------------------------------------------------------------------------------------------

Dim = int | str
"""One entry of a declared array shape: a fixed size, or a symbol ("N", "H") on which every
field of the message using it must agree (bound by the first array checked, or by an int
field declared with ``dim=``)."""


class Ctx:
    """What the fields of one message share while it is checked or decoded: the bound shape
    symbols and, when decoding, the wire map and the values decoded so far (by wire name)."""

    def __init__(self, cls: Any, obj: dict[str, Any] | None = None) -> None:
        self.cls = cls
        self.obj: dict[str, Any] = obj if obj is not None else {}
        self.dims: dict[str, int] = {}
        self.values: dict[str, Any] = {}

    def shape(self, spec: tuple[Dim, ...]) -> tuple[int | None, ...]:
        return tuple(d if isinstance(d, int) else self.dims.get(d) for d in spec)

    def bind(self, spec: tuple[Dim, ...], shape: tuple[int, ...]) -> None:
        for d, n in zip(spec, shape, strict=True):
            if isinstance(d, str):
                self.dims.setdefault(d, int(n))


class Kind:
    """The type of a field. `check` validates (and normalises) a Python value, `encode` gives
    its wire value, `decode` reads a wire value. Scalars decode by checking, and payloads
    (`rank` > 0) are decoded after every scalar, so a bad header never costs an image decode."""

    TYPE_DOC: ClassVar[str] = ""
    rank: ClassVar[int] = 0
    """Decode order: 0 scalars, 1 payloads (arrays, images: in declaration order), 2 payloads
    decoded after the others (an image that another output may have to size)."""

    @property
    def doc(self) -> str:
        """The ``type`` column of this field's row in docs/reference/protocol.md."""
        return self.TYPE_DOC

    def check(self, name: str, value: Any, ctx: Ctx) -> Any:
        return value

    def encode(self, value: Any, msg: Any) -> Any:
        return value

    def decode(self, name: str, raw: Any, ctx: Ctx) -> Any:
        return self.check(name, raw, ctx)


class Derived(Kind):
    """A Python attribute that is no wire key of its own (its row has ``wire=None``)."""

    def derive(self, ctx: Ctx) -> Any:
        """Its value once the wire fields are decoded (`MISSING_VALUE`: the default)."""
        return MISSING_VALUE

    def put(self, wire: dict[str, Any], value: Any) -> None:
        """What it adds to the wire map (nothing by default)."""


@dataclass(frozen=True)
class Int(Kind):
    lo: int | None = None
    hi: int | None = None

    @property
    def doc(self) -> str:
        if self.lo is not None and self.hi is not None:
            return f"int {self.lo}..{self.hi}"
        if self.lo is not None:
            return f"int >= {self.lo}"
        return "int" if self.hi is None else f"int <= {self.hi}"

    def check(self, name: str, value: Any, ctx: Ctx) -> int:
        return check_int(name, value, self.lo, self.hi)


@dataclass(frozen=True)
class Float(Kind):
    lo: float | None = None
    positive: bool = False
    finite: bool = True

    @property
    def doc(self) -> str:
        if self.positive:
            return "float > 0"
        return "float" if self.lo is None else f"float >= {self.lo:g}"

    def check(self, name: str, value: Any, ctx: Ctx) -> float:
        out = check_float(name, value, finite=self.finite, lo=self.lo)
        if self.positive and not out > 0:
            raise bad(f"{name}: must be > 0, got {out}")
        return out


@dataclass(frozen=True)
class Bool(Kind):
    TYPE_DOC: ClassVar[str] = "bool"

    def check(self, name: str, value: Any, ctx: Ctx) -> bool:
        if isinstance(value, np.bool_):
            value = bool(value)
        if not isinstance(value, bool):
            raise bad(f"{name}: expected a bool, got {type_name(value)} {short(value)}")
        return value


@dataclass(frozen=True)
class Str(Kind):
    max_chars: int
    nonempty: bool = True

    TYPE_DOC: ClassVar[str] = "str"

    def check(self, name: str, value: Any, ctx: Ctx) -> str:
        return check_str(name, value, max_chars=self.max_chars, nonempty=self.nonempty)


@dataclass(frozen=True)
class OneOf(Kind):
    """A string from a fixed set."""

    choices: tuple[str, ...]

    @property
    def doc(self) -> str:
        return f"str ({', '.join(self.choices)})"

    def check(self, name: str, value: Any, ctx: Ctx) -> Any:
        if value not in self.choices:
            raise bad(f"{name}: {short(value)} unknown; allowed: {', '.join(self.choices)}")
        return value


@dataclass(frozen=True)
class Texts(Kind):
    """A list of min_count..max_count prompts, each a non-empty string of at most max_chars."""

    min_count: int
    max_count: int
    max_chars: int

    @property
    def doc(self) -> str:
        return f"[str] {self.min_count}..{self.max_count}"

    def check(self, name: str, value: Any, ctx: Ctx) -> list[str]:
        if not isinstance(value, list | tuple):
            raise bad(f"{name}: expected a list of strings, got {type_name(value)} {short(value)}")
        if not self.min_count <= len(value) <= self.max_count:
            raise bad(f"{name}: {len(value)} strings, allowed {self.min_count}..{self.max_count}")
        out = [check_str(f"{name}[{i}]", t, max_chars=self.max_chars) for i, t in enumerate(value)]
        for i, t in enumerate(out):
            if not t.strip():
                raise bad(f"{name}[{i}]: only whitespace; a prompt needs at least one word")
        return out

    def encode(self, value: Any, msg: Any) -> Any:
        return list(value)


@dataclass(frozen=True)
class Subset(Kind):
    """A non-empty list of distinct strings from a fixed set."""

    choices: tuple[str, ...]

    @property
    def doc(self) -> str:
        return f"[str] (subset of {', '.join(self.choices)})"

    def check(self, name: str, value: Any, ctx: Ctx) -> list[str]:
        if not isinstance(value, list | tuple) or not value:
            raise bad(
                f"{name}: expected a non-empty list, subset of {list(self.choices)}, got {short(value)}"
            )
        for item in value:
            if item not in self.choices:
                raise bad(f"{name}: {short(item)} unknown; allowed: {', '.join(self.choices)}")
        if len(set(value)) != len(value):
            raise bad(f"{name}: repeated entries in {list(value)}")
        return list(value)

    def encode(self, value: Any, msg: Any) -> Any:
        return list(value)


@dataclass(frozen=True)
class Vector(Kind):
    """A fixed count of finite numbers: a msgpack array on the wire (row-major), a float64
    array of `shape` in Python."""

    shape: tuple[int, ...]

    @property
    def doc(self) -> str:
        return f"{math.prod(self.shape)} floats"

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        arr = check_array(name, value, "float64", self.shape, coerce=True)
        if not np.all(np.isfinite(arr)):
            raise bad(f"{name}: values must be finite, got {arr.reshape(-1).tolist()}")
        return arr

    def encode(self, value: Any, msg: Any) -> Any:
        return [float(x) for x in value.reshape(-1)]

    def decode(self, name: str, raw: Any, ctx: Ctx) -> np.ndarray:
        return self.check(name, wire_numbers(name, raw, math.prod(self.shape)).reshape(self.shape), ctx)


@dataclass(frozen=True)
class Array(Kind):
    """An `nd` array: `dtype` in Python (converted to it if `coerce`), `wire_dtypes` on the wire."""

    dtype: str
    shape: tuple[Dim, ...]
    wire_dtypes: tuple[str, ...] = ()
    """Dtypes accepted on the wire; () = just `dtype`."""
    coerce: bool = True
    finite: str = ""
    """If set, NaN/Inf are rejected with "<name>: <finite> must be finite"."""

    rank: ClassVar[int] = 1

    @property
    def dtypes(self) -> tuple[str, ...]:
        return self.wire_dtypes or (self.dtype,)

    @property
    def doc(self) -> str:
        return f"nd {'/'.join(self.dtypes)} [{','.join(str(d) for d in self.shape)}]"

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        arr = check_array(name, value, self.dtype, ctx.shape(self.shape), coerce=self.coerce)
        ctx.bind(self.shape, arr.shape)
        if self.finite and not np.all(np.isfinite(arr)):
            raise bad(f"{name}: {self.finite} must be finite (got NaN or Inf)")
        return arr

    def encode(self, value: Any, msg: Any) -> Any:
        return encode_nd(value)

    def decode(self, name: str, raw: Any, ctx: Ctx) -> np.ndarray:
        arr = decode_nd(raw, field=name, dtypes=self.dtypes, shape=ctx.shape(self.shape))
        ctx.bind(self.shape, arr.shape)
        return arr


@dataclass(frozen=True)
class Image(Kind):
    """An (H, W, 3) uint8 RGB image; H, W are the message's shape symbols."""

    encoding_attr: str = ""
    """The attribute naming the encoding to send ("" = always rgb8)."""

    TYPE_DOC: ClassVar[str] = "image"
    rank: ClassVar[int] = 1
    SHAPE: ClassVar[tuple[Dim, ...]] = ("H", "W", 3)

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        arr = check_array(name, value, "uint8", ctx.shape(self.SHAPE))
        ctx.bind(self.SHAPE, arr.shape)
        return arr

    def encode(self, value: Any, msg: Any) -> Any:
        return encode_image(value, getattr(msg, self.encoding_attr) if self.encoding_attr else "rgb8")

    def decode(self, name: str, raw: Any, ctx: Ctx) -> np.ndarray:
        height, width = ctx.dims.get("H"), ctx.dims.get("W")
        if height is None or width is None:
            raise bad(f"{ctx.cls.TYPE}: {name} sent without width/height (or another output to size it)")
        return decode_image(raw, width=width, height=height, field=name)


@dataclass(frozen=True)
class LateImage(Image):
    """An image decoded after the message's arrays, which may give its size (a render reply)."""

    rank: ClassVar[int] = 2


@dataclass(frozen=True)
class ImageEncoding(Derived):
    """The encoding the image field `source` was received in, and is sent with."""

    source: str

    def check(self, name: str, value: Any, ctx: Ctx) -> Any:
        if value not in IMAGE_ENCODINGS:
            raise bad(f"{name}: {value!r} unknown; allowed {', '.join(IMAGE_ENCODINGS)}")
        return value

    def derive(self, ctx: Ctx) -> Any:
        return ctx.obj[self.source]["encoding"]


@dataclass(frozen=True)
class Rest(Derived):
    """Every wire key the message does not declare, flat on the wire (e.g. `Status.extra`)."""

    def check(self, name: str, value: Any, ctx: Ctx) -> dict[str, Any]:
        out = check_str_map(name, value)
        clash = sorted(set(out) & {"v", "type", *ctx.cls.WIRE_KEYS})
        if clash:
            raise bad(f"{name}: keys {clash} clash with the {ctx.cls.TYPE} message's own fields")
        return out

    def put(self, wire: dict[str, Any], value: Any) -> None:
        wire.update(value)

    def derive(self, ctx: Ctx) -> Any:
        own = {"v", "type", *ctx.cls.WIRE_KEYS}
        return {k: v for k, v in ctx.obj.items() if k not in own}


@dataclass(frozen=True)
class Timing(Kind):
    TYPE_DOC: ClassVar[str] = "map str -> float"

    def check(self, name: str, value: Any, ctx: Ctx) -> dict[str, float]:
        if not isinstance(value, Mapping):
            raise bad(f"{name}: expected a map of str -> number, got {type_name(value)}")
        out: dict[str, float] = {}
        for key, ms in value.items():
            if not isinstance(key, str):
                raise bad(f"{name}: keys must be strings, got {type_name(key)} {short(key)}")
            out[key] = check_float(f"{name}.{key}", ms, finite=False)
        return out

    def encode(self, value: Any, msg: Any) -> Any:
        return dict(value)


@dataclass(frozen=True)
class StrMap(Kind):
    """A free-form map with string keys and msgpack-able values."""

    TYPE_DOC: ClassVar[str] = "map"

    def check(self, name: str, value: Any, ctx: Ctx) -> dict[str, Any]:
        return check_str_map(name, value)

    def encode(self, value: Any, msg: Any) -> Any:
        return dict(value)


@dataclass(frozen=True)
class Objects(Kind):
    """A list of nested maps, each an `item` (a message class declared with ``NESTED = True``)."""

    item: Any

    @property
    def doc(self) -> str:
        return f"[{self.item.TYPE}]"

    def check(self, name: str, value: Any, ctx: Ctx) -> list[Any]:
        if not isinstance(value, list | tuple):
            raise bad(f"{name}: expected a list, got {type_name(value)}")
        for i, obj in enumerate(value):
            if not isinstance(obj, self.item):
                raise bad(f"{name}[{i}]: expected an {self.item.__name__}, got {type_name(obj)}")
        return list(value)

    def encode(self, value: Any, msg: Any) -> Any:
        return [obj.to_wire() for obj in value]

    def decode(self, name: str, raw: Any, ctx: Ctx) -> list[Any]:
        if not isinstance(raw, list):
            raise bad(f"{name}: expected a list, got {type_name(raw)}")
        out = []
        for i, obj in enumerate(raw):
            try:
                out.append(self.item.from_wire(obj))
            except ProtocolError as exc:
                raise bad(f"{name}[{i}]: {exc.message}") from None
        return out


@dataclass(frozen=True)
class Id(Kind):
    """The request id: an int (64-bit) or a string of at most `max_chars`; sent right after the header."""

    max_chars: int

    TYPE_DOC: ClassVar[str] = "int or str"

    def check(self, name: str, value: Any, ctx: Ctx) -> int | str | None:
        if value is None:
            return None
        if isinstance(value, np.integer):
            value = int(value)
        if is_int(value):
            return check_int(name, value)
        if isinstance(value, str):
            return check_str(name, value, max_chars=self.max_chars, nonempty=False)
        raise bad(f"{name}: expected an int or a string, got {type_name(value)} {short(value)}")


# ----------------------------------------------------------------------------------------------
# Field tables
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WireField:
    """One row of a message's field table (docs/reference/protocol.md shows the same rows)."""

    py: str | None
    """Python attribute; None for a wire-only key (`Frame`'s `depth_scale`)."""
    wire: str | None
    """Wire key; None for a Python-only attribute (`Frame.rgb_encoding`, `Status.extra`)."""
    kind: Kind
    unit: str = ""
    required: bool | str = True
    """True, False, or a condition: ``"with K"`` (required whenever key K is sent: a pair such
    as `RenderResult`'s height/width) or any other text, which the message's `_check` enforces
    (e.g. ``"if ov"``)."""
    default: Any = None
    """The value of an optional key that is absent or nil."""
    default_factory: Callable[[], Any] | None = None
    nullable: bool = False
    """None is a valid Python value (and is not checked)."""
    send_nil: bool = False
    """A None value is sent as nil rather than left out."""
    omit_default: bool = False
    """The default value is left out of the wire (a key added compatibly: a message that does not
    use it encodes to the same bytes as before the key existed)."""
    dim: str | None = None
    """The shape symbol an int field sets (`width` -> "W")."""
    before: str | None = None
    """Written to the wire just before this key (otherwise in declaration order, `id` first)."""
    value: Callable[[Any], Any] | None = None
    """For a wire-only key that is sent: its value, from the message."""
    doc: str = ""

    @property
    def name(self) -> str:
        """The name errors use: the wire key, or the attribute of a Python-only field."""
        return self.wire or self.py or "?"

    def required_in(self, obj: dict[str, Any]) -> bool:
        """Whether this key must be in wire map `obj` (then nil is a value, not absence)."""
        if isinstance(self.required, str) and self.required.startswith("with "):
            return self.required[5:] in obj or (self.wire or "") in obj
        return self.required is True

    def absent(self) -> Any:
        return self.default_factory() if self.default_factory is not None else self.default

    @property
    def row(self) -> tuple[str, str, str, str]:
        """(key, type, unit, required) as in docs/reference/protocol.md."""
        if self.required is True:
            required = "yes"
        elif isinstance(self.required, str):
            required = self.required
        else:
            default = self.absent()
            required = "no" if default is None else f"no (default {json.dumps(default)})"
        return self.name, self.kind.doc, self.unit, required


def wire(
    kind: Kind,
    *,
    name: str | None = None,
    unit: str = "",
    required: bool | str | None = None,
    default: Any = MISSING,
    default_factory: Any = MISSING,
    send_nil: bool = False,
    omit_default: bool = False,
    dim: str | None = None,
    before: str | None = None,
    doc: str = "",
) -> Any:
    """Declare a message field: a dataclass field carrying its row of the field table.

    `name` is the wire key (default: the attribute name); a field is required unless it has a
    default (or says ``required=False``, or gives a condition such as ``"if ov"``); with
    `omit_default` its default value is not sent.
    """
    spec = dict(
        kind=kind, name=name, unit=unit, required=required, send_nil=send_nil, omit_default=omit_default,
        dim=dim, before=before, doc=doc,
    )
    return field(default=default, default_factory=default_factory, metadata={"wire": spec})


def wire_only(
    name: str,
    kind: Kind,
    *,
    unit: str = "",
    required: bool | str = False,
    default: Any = None,
    dim: str | None = None,
    before: str | None = None,
    value: Callable[[Any], Any] | None = None,
    doc: str = "",
) -> WireField:
    """A wire key without a Python attribute (list it in the class's `WIRE_ONLY`)."""
    return WireField(
        None, name, kind, unit=unit, required=required, default=default, dim=dim, before=before, value=value,
        doc=doc,
    )


def _row(f: Any) -> WireField:
    spec = f.metadata.get("wire")
    if spec is None:
        raise TypeError(f"field {f.name!r}: declare it with wire(...)")
    has_default = f.default is not MISSING or f.default_factory is not MISSING
    kind = spec["kind"]
    return WireField(
        f.name,
        None if isinstance(kind, Derived) else spec["name"] or f.name,
        kind,
        unit=spec["unit"],
        required=spec["required"] if spec["required"] is not None else not has_default,
        default=None if f.default is MISSING else f.default,
        default_factory=None if f.default_factory is MISSING else f.default_factory,
        nullable=(f.default is None) or spec["send_nil"],
        send_nil=spec["send_nil"],
        omit_default=spec["omit_default"],
        dim=spec["dim"],
        before=spec["before"],
        doc=spec["doc"],
    )


def _encode_order(table: tuple[WireField, ...]) -> tuple[WireField, ...]:
    sent = [f for f in table if f.py is not None or f.value is not None]
    order = sorted(sent, key=lambda f: not isinstance(f.kind, Id))  # stable: `id` first
    for f in [f for f in order if f.before]:
        order.remove(f)
        order.insert(next(i for i, g in enumerate(order) if g.wire == f.before), f)
    return tuple(order)


T = TypeVar("T")


@dataclass_transform(eq_default=False, field_specifiers=(wire,))
def message(cls: type[T]) -> type[T]:
    """Make `cls` a dataclass and derive its field table from its `wire` fields (and
    `WIRE_ONLY`): sets `FIELDS`, `WIRE_KEYS` and the encode / decode orders."""
    out: Any = dataclass(eq=False, repr=False)(cls)
    table = tuple(_row(f) for f in fields(out)) + tuple(out.WIRE_ONLY)
    on_wire = sorted((f for f in table if f.wire), key=lambda f: f.kind.rank)
    out.FIELDS = table
    out.WIRE_KEYS = frozenset(f.wire for f in table if f.wire)
    out.ENCODE_ORDER = _encode_order(table)
    out.DECODE_ORDER = tuple(on_wire) + tuple(f for f in table if not f.wire)
    return cls


# ----------------------------------------------------------------------------------------------
# What the table gives: checks, encoding, decoding
# ----------------------------------------------------------------------------------------------


def check_fields(msg: Any) -> None:
    """Check (and normalise) every attribute of a constructed message, in declaration order."""
    ctx = Ctx(type(msg))
    for f in msg.FIELDS:
        if f.py is None:
            continue
        value = getattr(msg, f.py)
        if value is None and f.nullable:
            continue
        value = f.kind.check(f.name, value, ctx)
        if f.dim is not None:
            ctx.dims[f.dim] = value
        setattr(msg, f.py, value)


def fields_to_wire(msg: Any, wire: dict[str, Any]) -> dict[str, Any]:
    """Add the message's fields to `wire` (its header): `id` first, then declaration order
    (but see `WireField.before`); None values are left out unless `send_nil`, and default values
    of `omit_default` fields are left out."""
    for f in msg.ENCODE_ORDER:
        value = getattr(msg, f.py) if f.py is not None else f.value(msg)
        if f.wire is None:
            f.kind.put(wire, value)
        elif f.omit_default and value is not None and value == f.default:
            continue
        elif value is not None:
            wire[f.wire] = f.kind.encode(value, msg)
        elif f.send_nil:
            wire[f.wire] = None
    return wire


def fields_from_wire(cls: Any, obj: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The constructor arguments for `cls` from a wire map (header already checked).

    Missing required keys are reported first (``<prefix>missing required field 'k'``); then
    the scalars are decoded, then the payloads (`Kind.rank`). An optional key sent as nil
    counts as absent; unknown keys are ignored (or collected by a `Rest` field).
    """
    required = {f.wire for f in cls.FIELDS if f.wire and f.required_in(obj)}
    for f in cls.FIELDS:
        if f.wire in required and f.wire not in obj:
            raise bad(f"{prefix}missing required field {f.wire!r}")
    ctx = Ctx(cls, obj)
    kwargs: dict[str, Any] = {}
    for f in cls.DECODE_ORDER:
        if f.wire is None:
            value = f.kind.derive(ctx)
            if value is not MISSING_VALUE:
                kwargs[f.py] = value
            continue
        raw = obj.get(f.wire)
        value = f.absent() if f.wire not in required and raw is None else f.kind.decode(f.wire, raw, ctx)
        if f.dim is not None and value is not None:
            ctx.dims[f.dim] = value
        ctx.values[f.wire] = value
        if f.py is not None:
            kwargs[f.py] = value
    return kwargs

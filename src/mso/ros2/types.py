"""ROS 2 message types as msgspec Structs, so ROS messages travel mso's edges typed.

Every type in rosbags' type stores (and any registered from ``.msg`` text with
:func:`register`) gets a Struct generated from its field definitions, named as rosbags names
it: ``std_msgs/msg/String`` is ``std_msgs__msg__String``. Name it as an edge's format in an app
file, ``output: mso.ros2.types:std_msgs__msg__String``: this module makes the class on first
use. The mapping, field by field:

- ``bool`` -> ``bool``; integers, ``byte`` and ``char`` -> ``int``; ``float32/64`` -> ``float``;
  ``string``/``wstring`` -> ``str``; a nested message -> its Struct;
- ``uint8[]``/``byte[]`` (fixed or not: images, point clouds) -> ``bytes``;
- any other array or sequence -> a ``list`` of the above.

Every field has a default (zero, empty, a default nested message), so an operator can write
``sensor_msgs__msg__LaserScan(ranges=[...])``. Conversions to and from rosbags' dataclasses
(what its CDR serializer reads and writes) are :meth:`TypeMap.to_struct` and
:meth:`TypeMap.to_ros`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

_STORES = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "rolling": Stores.LATEST,
}
FORMATS_DISTRO = "jazzy"  # the store this module's attributes (the app's formats) come from

_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4  # rosbags' Nodetype values
_BYTES = {"uint8", "byte", "octet", "char"}
_FLOAT = {"float32", "float64"}
_DTYPES: dict[str, Any] = {
    "bool": np.bool_,
    "byte": np.uint8,
    "octet": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}
_registered: dict[str, str] = {}  # ROS type name -> .msg text, applied to every store
_lock = threading.Lock()


def struct_name(ros_type: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs__msg__String`` (rosbags' spelling)."""
    return ros_type.replace("/", "__")


def _scalar(base: str) -> tuple[Any, Any]:
    if base in ("string", "wstring"):
        return str, ""
    if base == "bool":
        return bool, False
    if base in _FLOAT:
        return float, 0.0
    return int, 0


class TypeMap:
    """The Structs of one distribution's type store, made once each, and the conversions."""

    def __init__(self, distro: str) -> None:
        if distro not in _STORES:
            raise ValueError(f"distro: expected one of {', '.join(_STORES)}, got {distro!r}")
        self.distro = distro
        self.store = get_typestore(_STORES[distro])
        self._structs: dict[str, type[msgspec.Struct]] = {}
        self._to_struct: dict[str, Callable[[Any], Any]] = {}
        self._to_ros: dict[str, Callable[[Any], Any]] = {}
        for name, text in list(_registered.items()):
            self._register(name, text)

    def _register(self, ros_type: str, msgdef: str) -> None:
        if ros_type not in self.store.fielddefs:
            self.store.register(get_types_from_msg(msgdef, ros_type))

    def known(self, ros_type: str) -> bool:
        return ros_type in self.store.fielddefs

    def check(self, ros_type: str) -> None:
        if not self.known(ros_type):
            raise ValueError(
                f"type {ros_type!r} is not in rosbags' {self.distro} type store; "
                "register its .msg text (the vertex's msgdef param)"
            )

    def rihs01(self, ros_type: str) -> str:
        self.check(ros_type)
        return str(self.store.hash_rihs01(ros_type))

    # -- the Struct of a type ----------------------------------------------------------------
    def struct(self, ros_type: str) -> type[msgspec.Struct]:
        """The Struct for ``ros_type`` (made on first use, then the same class)."""
        with _lock:
            return self._struct(ros_type)

    def _field(self, node: tuple[int, Any]) -> tuple[Any, Any]:
        """A field's annotation and its default (a value, or a factory wrapped in a list)."""
        kind, info = node
        if kind == _BASE:
            return _scalar(info[0])
        if kind == _NAME:
            nested = self._struct(info)
            return nested, [nested]
        sub, size = info
        if sub[0] == _BASE and sub[1][0] in _BYTES:
            return bytes, bytes(size) if kind == _ARRAY else b""
        item, default = self._field(sub)
        annotation: Any = list.__class_getitem__(item)  # list[item], made at run time
        if kind == _ARRAY:
            if isinstance(default, list):
                factory = default[0]
                return annotation, [lambda: [factory() for _ in range(size)]]
            return annotation, [lambda: [default] * size]
        return annotation, [list]

    def _struct(self, ros_type: str) -> type[msgspec.Struct]:
        cls = self._structs.get(ros_type)
        if cls is not None:
            return cls
        self.check(ros_type)
        fields = []
        for name, node in self.store.fielddefs[ros_type][1]:
            annotation, default = self._field(node)
            if isinstance(default, list):
                fields.append((name, annotation, msgspec.field(default_factory=default[0])))
            else:
                fields.append((name, annotation, default))
        made = msgspec.defstruct(
            struct_name(ros_type), fields, module=__name__, kw_only=True, omit_defaults=False
        )
        made.__doc__ = f"The ROS 2 message {ros_type} (generated from rosbags' type store)."
        self._structs[ros_type] = made
        return made

    # -- conversions ---------------------------------------------------------------------------
    def to_struct(self, ros_type: str, msg: Any) -> Any:
        """A rosbags dataclass (as its CDR deserializer returns it) -> the Struct."""
        with _lock:
            convert = self._converter(ros_type, True)
        return convert(msg)

    def to_ros(self, ros_type: str, event: Any) -> Any:
        """A Struct of this type, or a mapping of its fields -> rosbags' dataclass."""
        cls = self.struct(ros_type)
        if not isinstance(event, cls):
            event = msgspec.convert(
                event if isinstance(event, dict) else msgspec.to_builtins(event), cls
            )
        with _lock:
            convert = self._converter(ros_type, False)
        return convert(event)

    def _converter(self, ros_type: str, inbound: bool) -> Callable[[Any], Any]:
        cache = self._to_struct if inbound else self._to_ros
        fn = cache.get(ros_type)
        if fn is not None:
            return fn
        self.check(ros_type)
        cls = self._struct(ros_type) if inbound else self.store.types[ros_type]
        names: list[str] = []
        steps: list[Callable[[Any], Any] | None] = []
        for name, node in self.store.fielddefs[ros_type][1]:
            names.append(name)
            steps.append(self._step(node, inbound))

        def convert(obj: Any) -> Any:
            kwargs = {}
            for name, step in zip(names, steps, strict=True):
                value = getattr(obj, name)
                kwargs[name] = value if step is None else step(value)
            return cls(**kwargs)

        cache[ros_type] = convert
        return convert

    def _step(self, node: tuple[int, Any], inbound: bool) -> Callable[[Any], Any] | None:
        """How one field's value converts (None: as it is)."""
        kind, info = node
        if kind == _BASE:
            return None
        if kind == _NAME:
            # resolved when first called: a type may nest itself through a sequence
            nested: str = info

            def convert_nested(v: Any) -> Any:
                return self._converter(nested, inbound)(v)

            return convert_nested
        sub, _size = info
        if sub[0] == _BASE:
            base = sub[1][0]
            if base in ("string", "wstring"):
                return list
            dtype = _DTYPES[base]
            if base in _BYTES:
                return (
                    (lambda v: bytes(np.asarray(v, dtype=np.uint8)))
                    if inbound
                    else (lambda v: np.frombuffer(bytes(v), dtype=np.uint8))
                )
            if inbound:
                return lambda v: np.asarray(v).tolist()
            return lambda v: np.asarray(v, dtype=dtype)
        item = self._step(sub, inbound)
        assert item is not None
        return lambda v: [item(x) for x in v]


_maps: dict[str, TypeMap] = {}


def type_map(distro: str = FORMATS_DISTRO) -> TypeMap:
    """The shared :class:`TypeMap` of ``distro``."""
    with _lock:
        found = _maps.get(distro)
        if found is None:
            found = _maps[distro] = TypeMap(distro)
        return found


def register(ros_type: str, msgdef: str) -> None:
    """Add a custom message type from its ``.msg`` text (e.g. ``my_pkg/msg/Blob``) to every
    distribution's store; nested custom types must be registered first."""
    with _lock:
        known = _registered.get(ros_type)
        if known is not None and known != msgdef:
            raise ValueError(f"type {ros_type!r} is already registered with another definition")
        _registered[ros_type] = msgdef
        for tm in _maps.values():
            tm._register(ros_type, msgdef)


def struct_for(ros_type: str, distro: str = FORMATS_DISTRO) -> type[msgspec.Struct]:
    """The Struct that carries ``ros_type`` on mso's edges."""
    return type_map(distro).struct(ros_type)


def __getattr__(name: str) -> type[msgspec.Struct]:
    """``mso.ros2.types:std_msgs__msg__String``: the format named in an app file."""
    parts = name.split("__")
    if len(parts) != 3 or not all(parts):
        raise AttributeError(name)
    tm = type_map()
    ros_type = "/".join(parts)
    if not tm.known(ros_type):
        raise AttributeError(f"no ROS 2 message type {ros_type!r} (module {__name__!r})")
    cls = tm.struct(ros_type)
    globals()[name] = cls  # found under its own name from now on, as the allowlist checks
    return cls

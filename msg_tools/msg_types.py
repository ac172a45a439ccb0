"""Build ROS messages in either of the two Python flavours we meet.

The node talks rclpy (``sensor_msgs.msg.PointCloud2``, ``data`` an ``array.array('B')``); the
command line reads and writes bags with rosbags (typestore dataclasses, ``data`` a numpy uint8
array, every constructor field required). Readers in msg_tools are duck-typed and accept both;
writers take a :class:`MessageTypes` (``RCLPY`` or ``ROSBAGS``) that knows where the classes come
from and how to store bytes. The flavour's packages are imported on first use only, so code that
writes bags never needs rclpy, and the node never pays for the rosbags typestore.
"""
from __future__ import annotations

import array
import importlib
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

__all__ = [
    "MessageTypes",
    "RclpyTypes",
    "RosbagsTypes",
    "RCLPY",
    "ROSBAGS",
    "types_for",
    "msgtype_of",
    "stamp_ns",
]


class MessageTypes:
    """Factory for the message classes of one flavour.

    Subclasses only say where a class comes from (:meth:`cls`) and how a uint8 sequence is
    stored (:meth:`uint8`); every builder passes every field explicitly, which is what rosbags
    requires and what rclpy accepts.
    """

    name = "abstract"

    def cls(self, msgtype: str) -> type:
        """The class for ``msgtype`` (``"sensor_msgs/msg/PointCloud2"``)."""
        raise NotImplementedError

    def uint8(self, buf: Any) -> Any:
        """A value for a ``uint8[]`` field holding the bytes of ``buf`` (bytes-like)."""
        raise NotImplementedError

    def uint8_buffer(self, nbytes: int) -> tuple[Any, np.ndarray]:
        """An ``nbytes``-long value for a ``uint8[]`` field and a writable numpy view of its
        memory: a writer fills the field in place instead of filling an array and copying it
        (a 640x480 segmented cloud is 7.4 MB)."""
        buf = np.empty(int(nbytes), dtype=np.uint8)
        return self.uint8(buf), buf

    def owns(self, msg: Any) -> bool:
        """True when ``msg`` is an instance of this flavour."""
        raise NotImplementedError

    def _bytes_message(self, msgtype: str, data: Any, **fields: Any) -> Any:
        """A message with a (large) uint8[] ``data`` field: PointCloud2, CompressedImage."""
        return self.cls(msgtype)(data=self.uint8(data), **fields)

    # -- builtin_interfaces / std_msgs -------------------------------------------------------
    def time(self, sec: int = 0, nanosec: int = 0) -> Any:
        return self.cls("builtin_interfaces/msg/Time")(sec=int(sec), nanosec=int(nanosec))

    def duration(self, sec: int = 0, nanosec: int = 0) -> Any:
        return self.cls("builtin_interfaces/msg/Duration")(sec=int(sec), nanosec=int(nanosec))

    def header(self, frame_id: str = "", sec: int = 0, nanosec: int = 0) -> Any:
        return self.cls("std_msgs/msg/Header")(stamp=self.time(sec, nanosec), frame_id=str(frame_id))

    def header_from(self, header: Any) -> Any:
        """Copy a header of either flavour into this flavour (outputs keep the input's stamp)."""
        if self.owns(header):
            return header
        return self.header(header.frame_id, header.stamp.sec, header.stamp.nanosec)

    def color_rgba(self, r: float, g: float, b: float, a: float = 1.0) -> Any:
        return self.cls("std_msgs/msg/ColorRGBA")(r=float(r), g=float(g), b=float(b), a=float(a))

    # -- sensor_msgs ---------------------------------------------------------------------------
    def point_field(self, name: str, offset: int, datatype: int, count: int = 1) -> Any:
        return self.cls("sensor_msgs/msg/PointField")(
            name=str(name), offset=int(offset), datatype=int(datatype), count=int(count)
        )

    def point_cloud2(
        self,
        header: Any,
        height: int,
        width: int,
        fields: Sequence[Any],
        is_bigendian: bool,
        point_step: int,
        row_step: int,
        data: Any,
        is_dense: bool = False,
    ) -> Any:
        """A PointCloud2; ``fields`` may be of either flavour, ``data`` any bytes-like."""
        return self._bytes_message(
            "sensor_msgs/msg/PointCloud2",
            data,
            header=self.header_from(header),
            height=int(height),
            width=int(width),
            fields=[self.point_field(f.name, f.offset, f.datatype, f.count) for f in fields],
            is_bigendian=bool(is_bigendian),
            point_step=int(point_step),
            row_step=int(row_step),
            is_dense=bool(is_dense),
        )

    def compressed_image(self, header: Any = None, format: str = "", data: Any = b"") -> Any:
        return self._bytes_message(
            "sensor_msgs/msg/CompressedImage",
            data,
            header=self.header() if header is None else self.header_from(header),
            format=str(format),
        )

    # -- geometry_msgs -------------------------------------------------------------------------
    def point(self, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
        return self.cls("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=float(z))

    def vector3(self, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
        return self.cls("geometry_msgs/msg/Vector3")(x=float(x), y=float(y), z=float(z))

    def quaternion(self, x: float = 0.0, y: float = 0.0, z: float = 0.0, w: float = 1.0) -> Any:
        return self.cls("geometry_msgs/msg/Quaternion")(x=float(x), y=float(y), z=float(z), w=float(w))

    def pose(
        self,
        position: Sequence[float] = (0.0, 0.0, 0.0),
        orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> Any:
        """A Pose from ``(x, y, z)`` and a quaternion ``(x, y, z, w)`` (default identity)."""
        return self.cls("geometry_msgs/msg/Pose")(
            position=self.point(*position), orientation=self.quaternion(*orientation)
        )

    def pose_array(self, header: Any, poses: Iterable[Any]) -> Any:
        return self.cls("geometry_msgs/msg/PoseArray")(header=self.header_from(header), poses=list(poses))

    # -- visualization_msgs --------------------------------------------------------------------
    def marker(
        self,
        header: Any,
        ns: str = "",
        id: int = 0,
        type: int = 0,
        action: int = 0,
        pose: Any = None,
        scale: Any = None,
        color: Any = None,
        text: str = "",
        lifetime: Any = None,
        frame_locked: bool = False,
    ) -> Any:
        """A Marker; unset pose/scale/color/lifetime become identity, zeros, transparent, forever."""
        return self.cls("visualization_msgs/msg/Marker")(
            header=self.header_from(header),
            ns=str(ns),
            id=int(id),
            type=int(type),
            action=int(action),
            pose=self.pose() if pose is None else pose,
            scale=self.vector3() if scale is None else scale,
            color=self.color_rgba(0.0, 0.0, 0.0, 0.0) if color is None else color,
            lifetime=self.duration() if lifetime is None else lifetime,
            frame_locked=bool(frame_locked),
            points=[],
            colors=[],
            texture_resource="",
            texture=self.compressed_image(),
            uv_coordinates=[],
            text=str(text),
            mesh_resource="",
            mesh_file=self.cls("visualization_msgs/msg/MeshFile")(filename="", data=self.uint8(b"")),
            mesh_use_embedded_materials=False,
        )

    def marker_array(self, markers: Iterable[Any]) -> Any:
        return self.cls("visualization_msgs/msg/MarkerArray")(markers=list(markers))

    def __repr__(self) -> str:
        return f"<MessageTypes {self.name}>"


class RclpyTypes(MessageTypes):
    """rclpy message classes (``sensor_msgs.msg`` ...), imported on first use."""

    name = "rclpy"

    def __init__(self) -> None:
        self._cache: dict[str, type] = {}

    def cls(self, msgtype: str) -> type:
        try:
            return self._cache[msgtype]
        except KeyError:
            pass
        pkg, _, name = msgtype.split("/")
        try:
            found = getattr(importlib.import_module(f"{pkg}.msg"), name)
        except (ImportError, AttributeError) as err:
            raise ImportError(
                f"rclpy message class {msgtype!r} is not importable ({err}); source a ROS 2 Jazzy "
                f"environment or install the ros-jazzy interface wheels (requirements/runtime.txt)"
            ) from err
        self._cache[msgtype] = found
        return found

    def _bytes_message(self, msgtype: str, data: Any, **fields: Any) -> Any:
        # rclpy's generated constructor copies a uint8[] argument (array.array('B', data)), and
        # so does the field's setter unless the message checks its fields; checked, the setter
        # keeps an array.array('B') as it is. The other checks are isinstance tests on a few
        # fields. Two 7.4 MB copies less per 640x480 segmented cloud.
        msg = self.cls(msgtype)(check_fields=True, **fields)
        msg.data = self.uint8(data)
        return msg

    def uint8_buffer(self, nbytes: int) -> tuple[Any, np.ndarray]:
        out = array.array("B", bytes(1)) * int(nbytes)
        return out, np.frombuffer(out, dtype=np.uint8)

    def uint8(self, buf: Any) -> Any:
        # array.array('B', bytes) is a single memcpy; rclpy's setter accepts it without a per-
        # element check. Never pass a numpy array here: rclpy would iterate it element-wise.
        if isinstance(buf, array.array) and buf.typecode == "B":
            return buf
        if isinstance(buf, np.ndarray):
            buf = np.ascontiguousarray(buf)
        out = array.array("B")
        out.frombytes(memoryview(buf).cast("B"))
        return out

    def owns(self, msg: Any) -> bool:
        return not hasattr(type(msg), "__msgtype__") and hasattr(type(msg), "get_fields_and_field_types")


class RosbagsTypes(MessageTypes):
    """rosbags typestore dataclasses (default: ROS 2 Jazzy store), created on first use."""

    name = "rosbags"

    def __init__(self, typestore: Any = None) -> None:
        self._typestore = typestore

    @property
    def typestore(self) -> Any:
        """The rosbags typestore; also used by msg_tools.bag to (de)serialize."""
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.ROS2_JAZZY)
        return self._typestore

    def cls(self, msgtype: str) -> type:
        try:
            return self.typestore.types[msgtype]
        except KeyError:
            raise KeyError(
                f"message type {msgtype!r} is not in the rosbags typestore; register it first "
                f"(typestore.register(get_types_from_msg(...)))"
            ) from None

    def uint8(self, buf: Any) -> Any:
        if isinstance(buf, np.ndarray):
            return np.ascontiguousarray(buf).view(np.uint8).reshape(-1)
        return np.frombuffer(buf, dtype=np.uint8)

    def owns(self, msg: Any) -> bool:
        return hasattr(type(msg), "__msgtype__")


RCLPY = RclpyTypes()
ROSBAGS = RosbagsTypes()


def types_for(msg: Any) -> MessageTypes:
    """The flavour of ``msg``, so outputs can match their input (rosbags in, rosbags out)."""
    return ROSBAGS if hasattr(type(msg), "__msgtype__") else RCLPY


def msgtype_of(msg: Any) -> str:
    """``"pkg/msg/Name"`` for a message of either flavour."""
    msgtype = getattr(type(msg), "__msgtype__", None)
    if msgtype:
        return str(msgtype)
    module = type(msg).__module__.split(".")
    if len(module) < 2 or module[1] != "msg":
        raise TypeError(f"{type(msg).__qualname__} is not a ROS message class (module {type(msg).__module__})")
    return f"{module[0]}/msg/{type(msg).__name__}"


def stamp_ns(header: Any) -> int:
    """Header stamp in integer nanoseconds (either flavour)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)

"""The ROS 2 messages curlnav speaks, from their ``.msg`` definitions (ROS 2 Humble's
common_interfaces, comments dropped): one text per type is the one source for the DDS types
(``dds_type``: ``sensor_msgs::msg::dds_::LaserScan_``, as ``rmw_cyclonedds`` and
``rmw_fastrtps`` name them on the wire) and for the MCAP schemas (``schema_text``: the text with
its dependencies, as ``ros2 bag`` writes it).

Units follow REP 103: metres, radians, seconds; x forward, y left, z up.
"""

from __future__ import annotations

import math
import re
from functools import cache

#: ``pkg/msg/Name`` -> its ``.msg`` text; a type of the same package may go unqualified.
MSG = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/Float64": "float64 data\n",
    "std_msgs/msg/String": "string data\n",
    # Empty.msg has no field; rosidl gives every empty struct this one (on the wire and in IDL)
    "std_msgs/msg/Empty": "uint8 structure_needs_at_least_one_member\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/msg/LaserScan": (
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
        "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
        "float32[] ranges\nfloat32[] intensities\n"),
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"),
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    "nav_msgs/msg/MapMetaData": (
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n"
        "geometry_msgs/Pose origin\n"),
    "nav_msgs/msg/OccupancyGrid": "std_msgs/Header header\nMapMetaData info\nint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\nint32 LINE_LIST=5\n"
        "int32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\nint32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\n"
        "int32 TRIANGLE_LIST=11\nint32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
        "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring text\n"
        "string mesh_resource\nbool mesh_use_embedded_materials\n"),
    "visualization_msgs/msg/MarkerArray": "Marker[] markers\n",
}

_PRIMITIVES = ("bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string")
_CONSTANT = re.compile(r"^\S+\s+[A-Z][A-Z0-9_]*\s*=")
_FIELD = re.compile(r"^(?P<type>[A-Za-z0-9_/]+(?:<=\d+)?)(?P<array>\[(?:<=)?\d*\])?\s+(?P<name>[a-z][a-z0-9_]*)(?:\s+.*)?$")


def fields_of(name: str) -> list[tuple[str, str, str | None]]:
    """``[(field, type, array)]`` of ``pkg/msg/Name``: ``type`` a primitive or ``pkg/msg/Name``,
    ``array`` None, ``"[]"``, ``"[N]"`` or ``"[<=N]"``. Constants are left out."""
    package = name.split("/")[0]
    out = []
    for raw in MSG[name].splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line or _CONSTANT.match(line):
            continue
        match = _FIELD.match(line)
        if match is None:
            raise ValueError(f"{name}: cannot read the line {raw!r}")
        kind = match["type"].split("<=")[0]
        if kind not in _PRIMITIVES:
            parts = kind.split("/")
            kind = f"{package}/msg/{parts[0]}" if len(parts) == 1 else f"{parts[0]}/msg/{parts[-1]}"
        out.append((match["name"], kind, match["array"]))
    return out


def dependencies(name: str) -> list[str]:
    """Every message type ``name`` uses, depth first, each once."""
    seen: list[str] = []

    def visit(kind: str) -> None:
        for _, sub, _ in fields_of(kind):
            if sub not in _PRIMITIVES and sub not in seen:
                seen.append(sub)
                visit(sub)

    visit(name)
    return seen


def schema_text(name: str) -> str:
    """The ``ros2msg`` schema of ``name``: its text, then each dependency's after a line of 80
    ``=`` and ``MSG: pkg/Name`` (what MCAP readers and Foxglove expect)."""
    parts = [MSG[name].rstrip("\n")]
    for dep in dependencies(name):
        package, _, short = dep.split("/")
        parts.append("=" * 80 + f"\nMSG: {package}/{short}\n" + MSG[dep].rstrip("\n"))
    return "\n".join(parts) + "\n"


def dds_type_name(name: str) -> str:
    """``sensor_msgs/msg/LaserScan`` -> ``sensor_msgs::msg::dds_::LaserScan_`` (the ROS 2 rmw mapping)."""
    package, sub, short = name.split("/")
    return f"{package}::{sub}::dds_::{short}_"


@cache
def dds_type(name: str):
    """The Cyclone DDS ``IdlStruct`` class of ``pkg/msg/Name``, built from its ``.msg`` text."""
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl import types as t

    primitive = {"bool": bool, "byte": t.uint8, "char": t.uint8, "float32": t.float32, "float64": t.float64,
                 "int8": t.int8, "uint8": t.uint8, "int16": t.int16, "uint16": t.uint16, "int32": t.int32,
                 "uint32": t.uint32, "int64": t.int64, "uint64": t.uint64, "string": str}
    fields = {}
    for field, kind, array in fields_of(name):
        base = primitive[kind] if kind in primitive else dds_type(kind)
        if array is None:
            fields[field] = base
        elif array == "[]":
            fields[field] = t.sequence[base]
        elif array.startswith("[<="):
            fields[field] = t.sequence[base, int(array[3:-1])]
        else:
            fields[field] = t.array[base, int(array[1:-1])]
    return make_idl_struct(name.split("/")[-1] + "_", dds_type_name(name), fields)


# -- building and reading messages (dicts for MCAP, IdlStructs for DDS) ----------------------------------
def stamp(t_s: float) -> dict:
    """``builtin_interfaces/Time`` of ``t_s`` seconds."""
    sec = math.floor(t_s)
    return {"sec": int(sec), "nanosec": min(int(round((t_s - sec) * 1e9)), 999_999_999)}


def quaternion(yaw: float) -> dict:
    """A rotation of ``yaw`` rad about z."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def yaw_of(q) -> float:
    """The yaw (rad) of a quaternion (object with x, y, z, w)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def build(name: str, value: dict):
    """The ``dds_type(name)`` object of a nested dict (missing fields: zero, empty, identity)."""
    cls = dds_type(name)
    kwargs = {}
    for field, kind, array in fields_of(name):
        given = value.get(field)
        if kind not in _PRIMITIVES:
            if array is None:
                kwargs[field] = build(kind, given or {})
            else:
                kwargs[field] = [build(kind, v) for v in (given or [])]
        elif array is not None:
            size = int(array[1:-1]) if array[1:-1].isascii() and array[1:-1].isdigit() else 0
            kwargs[field] = list(given) if given is not None else [0.0] * size
        elif given is not None:
            kwargs[field] = given
        else:
            kwargs[field] = _default(name, field, kind)
    return cls(**kwargs)


def _default(name: str, field: str, kind: str):
    if kind == "string":
        return ""
    if kind == "bool":
        return False
    if kind.startswith("float"):
        return 1.0 if (name, field) == ("geometry_msgs/msg/Quaternion", "w") else 0.0
    return 0

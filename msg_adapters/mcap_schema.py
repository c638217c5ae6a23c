"""MCAP conventions of rosbag2 (Jazzy, storage plugin ``mcap``), built from the installed types.

What a rosbag2-compatible MCAP file carries, and where each piece comes from here:

* Header: profile ``ros2``; the library string is free-form (rosbag2 writes ``libmcap x.y.z``).
* Schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data = the *complete*
  message definition (:func:`message_definition`): the type's own ``.msg`` text, then every
  type it uses (sorted by the name written in the field, depth first, each once), behind a
  newline, a line of 80 ``=`` and a ``MSG: pkg/Type`` line. The text is read from the
  ``.msg`` files of the installed packages found through the ament index, exactly as
  rosbag2's ``LocalMessageDefinitionSource`` does.
* Channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles`` (the QoS of
  the publishers seen, YAML text as rosbag2 Jazzy writes it, :func:`offered_qos_profiles_yaml`)
  and ``topic_type_hash`` (the RIHS01 type hash, :func:`type_hash`).
* A metadata record ``rosbag2`` with ``serialized_metadata`` (the bag's metadata.yaml content,
  version 9), written when the file is closed (:func:`rosbag2_serialized_metadata`).

Service events (``<service>/_service_event``, type ``pkg/srv/Srv_Event``) have no ``.msg`` file:
rosbag2 Jazzy stores the raw ``.srv`` text behind an ``SRV:`` line there, which no decoder can
use (ros2/rosbag2#1966, #2365). Here the event is described as the message it is
(``info``, ``request[<=1]``, ``response[<=1]``), with the request and response halves of the
``.srv`` file as ``MSG: pkg/Srv_Request`` and ``MSG: pkg/Srv_Response`` sections (two-part
names: the .msg parsers of mcap-ros2-support and rosbags accept no ``srv`` in a field type).
rosbags decodes these events once the ``pkg/srv/Srv_Event`` name is registered (its type system
files it as ``pkg/srv/msg/Srv_Event``); mcap-ros2-support 0.6 rejects any message name with an
underscore, so no schema text makes it decode a service event.

No ROS client library is needed: this module reads files only.
"""
from __future__ import annotations

import json
import math
import os
import re
import struct
import sys
from functools import lru_cache
from typing import Iterable, Mapping, Sequence

import numpy as np

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
SERVICE_EVENT_SUFFIX = '/_service_event'
ROSBAG2_METADATA_NAME = 'rosbag2'
ROSBAG2_METADATA_VERSION = 9  # Jazzy: QoS policies serialised by name

SEPARATOR = '=' * 80 + '\n'

# rosbag2_cpp local_message_definition_source.cpp: field types of a .msg text.
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
# rosbag2's list, plus wstring (rosbag2 would look for a type called "wstring" and give up).
_PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'})
_NAME = r'[a-zA-Z][a-zA-Z0-9_]*'
_TYPE_NAME = re.compile(rf'^({_NAME})/(?:({_NAME})/)?({_NAME})$')

# rmw's RMW_DURATION_INFINITE as rosbag2 stores it.
_INFINITE_SEC = 9223372036
_INFINITE_NSEC = 854775807
_HISTORY = {0: 'system_default', 1: 'keep_last', 2: 'keep_all'}
_RELIABILITY = {0: 'system_default', 1: 'reliable', 2: 'best_effort', 4: 'best_available'}
_DURABILITY = {0: 'system_default', 1: 'transient_local', 2: 'volatile', 4: 'best_available'}
_LIVELINESS = {0: 'system_default', 1: 'automatic', 3: 'manual_by_topic', 5: 'best_available'}


class SchemaError(LookupError):
    """A type whose definition cannot be found in the installed packages; says which."""


def split_type_name(type_name: str) -> tuple[str, str, str]:
    """Split ``pkg/msg/Type`` (or ``pkg/Type``) into package, namespace and name."""
    match = _TYPE_NAME.match(type_name)
    if not match:
        raise SchemaError(f'not a ROS type name: {type_name!r} (expected pkg/msg/Type)')
    package, namespace, name = match.groups()
    return package, namespace or 'msg', name


def is_service_event_type(type_name: str) -> bool:
    """True for the introspection event type of a service, ``pkg/srv/Srv_Event``."""
    try:
        _, namespace, name = split_type_name(type_name)
    except SchemaError:
        return False
    return namespace == 'srv' and name.endswith('_Event')


def service_event_topic(service_name: str) -> str:
    """The topic on which a service publishes its introspection events."""
    return service_name.rstrip('/') + SERVICE_EVENT_SUFFIX


def share_directory(package: str) -> str:
    """share/<package> through the ament index; the running prefix (a venv with the ROS wheels)
    when AMENT_PREFIX_PATH is not set."""
    from ament_index_python.packages import (
        get_package_share_directory, PackageNotFoundError)
    try:
        return get_package_share_directory(package)
    except (PackageNotFoundError, LookupError, ValueError, OSError) as err:
        marker = os.path.join(sys.prefix, 'share', 'ament_index', 'resource_index', 'packages',
                              package)
        if os.path.exists(marker):
            return os.path.join(sys.prefix, 'share', package)
        raise SchemaError(
            f'package {package!r} not found in the ament index '
            f'(AMENT_PREFIX_PATH={os.environ.get("AMENT_PREFIX_PATH", "")!r}): {err}') from None


def _read(path: str, type_name: str) -> str:
    try:
        with open(path, encoding='utf-8') as stream:
            return stream.read()
    except OSError:
        raise SchemaError(f'no definition of {type_name} ({path} is missing)') from None


@lru_cache(maxsize=None)
def _srv_halves(package: str, service: str) -> tuple[str, str]:
    text = _read(os.path.join(share_directory(package), 'srv', service + '.srv'),
                 f'{package}/srv/{service}')
    parts = re.split(r'^---[ \t]*\r?\n?', text, maxsplit=1, flags=re.MULTILINE)
    if len(parts) != 2:
        raise SchemaError(f'{package}/srv/{service}.srv has no "---" line')
    return parts[0], parts[1]


def _service_part(package: str, name: str) -> str | None:
    """Text of ``Srv_Request``, ``Srv_Response`` or ``Srv_Event`` of a service, else None."""
    for suffix in ('_Request', '_Response', '_Event'):
        if not name.endswith(suffix):
            continue
        service = name[:-len(suffix)]
        request, response = _srv_halves(package, service)
        if suffix == '_Request':
            return request
        if suffix == '_Response':
            return response
        # The generated event type; two-part names, which every .msg parser accepts.
        return (f'service_msgs/ServiceEventInfo info\n'
                f'{package}/{service}_Request[<=1] request\n'
                f'{package}/{service}_Response[<=1] response\n')
    return None


@lru_cache(maxsize=None)
def _definition_text(type_name: str) -> str:
    """The text of one type, as its .msg file (or .srv half, or event) has it."""
    package, namespace, name = split_type_name(type_name)
    if namespace == 'srv':
        text = _service_part(package, name)
        if text is None:
            raise SchemaError(f'{type_name} is a service, not a message type')
        return text
    path = os.path.join(share_directory(package), namespace, name + '.msg')
    if namespace == 'msg' and not os.path.exists(path):
        # "pkg/Srv_Request" as written in an event definition
        text = _service_part(package, name)
        if text is not None:
            return text
    return _read(path, type_name)


def _dependencies(text: str, package: str) -> list[str]:
    found = set()
    for match in _FIELD_TYPE.finditer(text):
        field_type = match.group(1)
        if field_type in _PRIMITIVES:
            continue
        found.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(found)  # rosbag2 keeps them in a std::set


@lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """Complete ``ros2msg`` definition of a message type, as rosbag2 writes it in a schema.

    The type's text, then for each type it uses (sorted by name as written in the field,
    depth first, each once) a newline, 80 ``=``, ``MSG: <name as written>`` and its text.
    Raises :class:`SchemaError` naming the missing type or package.
    """
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise SchemaError(f'definition of {type_name} nests too deeply')
        text = _definition_text(name)
        out = [text]
        for dep in _dependencies(text, split_type_name(name)[0]):
            if dep in seen:  # rosbag2 keys on the name as written in the field
                continue
            seen.add(dep)
            out.append('\n' + SEPARATOR + f'MSG: {dep}\n' + append(dep, depth - 1))
        return ''.join(out)

    return append(type_name, 50)


@lru_cache(maxsize=None)
def _hashes_file(package: str, namespace: str, name: str) -> dict:
    path = os.path.join(share_directory(package), namespace, name + '.json')
    try:
        with open(path, encoding='utf-8') as stream:
            data = json.load(stream)
    except (OSError, ValueError):
        return {}
    return {entry['type_name']: entry['hash_string']
            for entry in data.get('type_hashes', [])
            if 'type_name' in entry and 'hash_string' in entry}


def type_hash(type_name: str) -> str:
    """RIHS01 type hash of a type from the installed type description (``.json``), or ''.

    Service request, response and event types are looked up in the service's file.
    """
    package, namespace, name = split_type_name(type_name)
    full = f'{package}/{namespace}/{name}'
    owner = name
    if namespace == 'srv':
        owner = re.sub(r'_(Request|Response|Event)$', '', name)
    return _hashes_file(package, namespace, owner).get(full, '')


def _policy(value, names: Mapping[int, str]) -> str:
    number = int(getattr(value, 'value', value))
    return names.get(number, 'unknown')


def _duration(value) -> tuple[int, int]:
    """(sec, nsec) of an rclpy Duration, a number of nanoseconds or a (sec, nsec) pair."""
    if value is None:
        return 0, 0
    if isinstance(value, (tuple, list)):
        return int(value[0]), int(value[1])
    nanoseconds = getattr(value, 'nanoseconds', value)
    if isinstance(nanoseconds, float) and math.isinf(nanoseconds):
        return _INFINITE_SEC, _INFINITE_NSEC
    nanoseconds = int(nanoseconds)
    if nanoseconds >= _INFINITE_SEC * 10**9 + _INFINITE_NSEC:
        return _INFINITE_SEC, _INFINITE_NSEC
    return divmod(nanoseconds, 10**9)


def qos_profile_to_dict(profile) -> dict:
    """One QoS profile (rclpy QoSProfile or alike) as rosbag2 Jazzy serialises it."""
    deadline = _duration(getattr(profile, 'deadline', None))
    lifespan = _duration(getattr(profile, 'lifespan', None))
    lease = _duration(getattr(profile, 'liveliness_lease_duration', None))
    return {
        'history': _policy(profile.history, _HISTORY),
        'depth': int(profile.depth or 0),
        'reliability': _policy(profile.reliability, _RELIABILITY),
        'durability': _policy(profile.durability, _DURABILITY),
        'deadline': {'sec': deadline[0], 'nsec': deadline[1]},
        'lifespan': {'sec': lifespan[0], 'nsec': lifespan[1]},
        'liveliness': _policy(profile.liveliness, _LIVELINESS),
        'liveliness_lease_duration': {'sec': lease[0], 'nsec': lease[1]},
        'avoid_ros_namespace_conventions': bool(
            getattr(profile, 'avoid_ros_namespace_conventions', False)),
    }


def offered_qos_profiles_yaml(profiles: Iterable) -> str:
    """YAML text of ``offered_qos_profiles`` as rosbag2 Jazzy writes it (yaml-cpp block style).

    ``profiles`` are rclpy QoSProfiles (e.g. ``TopicEndpointInfo.qos_profile`` of the
    publishers) or dicts from :func:`qos_profile_to_dict`. No profile gives ``[]``.
    """
    items = [p if isinstance(p, Mapping) else qos_profile_to_dict(p) for p in profiles]
    if not items:
        return '[]'
    lines = []
    for item in items:
        first = True
        for key in ('history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
                    'liveliness', 'liveliness_lease_duration',
                    'avoid_ros_namespace_conventions'):
            value = item[key]
            lead = '- ' if first else '  '
            first = False
            if isinstance(value, Mapping):
                lines.append(f'{lead}{key}:')
                lines.append(f'    sec: {int(value["sec"])}')
                lines.append(f'    nsec: {int(value["nsec"])}')
            elif isinstance(value, bool):
                lines.append(f'{lead}{key}: {"true" if value else "false"}')
            else:
                lines.append(f'{lead}{key}: {value}')
    return '\n'.join(lines)


def channel_metadata(type_name: str, qos_profiles: Iterable = (),
                     topic_type_hash: str | None = None) -> dict[str, str]:
    """Channel metadata rosbag2 Jazzy writes: ``offered_qos_profiles`` and ``topic_type_hash``.

    ``topic_type_hash`` defaults to :func:`type_hash` of the installed type.
    """
    return {
        'offered_qos_profiles': offered_qos_profiles_yaml(qos_profiles),
        'topic_type_hash': type_hash(type_name) if topic_type_hash is None else topic_type_hash,
    }


def rosbag2_serialized_metadata(
        file_name: str, topics: Sequence[Mapping], start_ns: int, end_ns: int,
        ros_distro: str | None = None) -> str:
    """YAML of the bag metadata (version 9) stored in the ``rosbag2`` metadata record.

    ``topics``: dicts with ``name``, ``type``, ``offered_qos_profiles`` (list of dicts from
    :func:`qos_profile_to_dict`), ``type_description_hash`` and ``message_count``.
    """
    import yaml

    count = sum(int(t['message_count']) for t in topics)
    start = int(start_ns) if count else 0
    duration = max(0, int(end_ns) - int(start_ns)) if count else 0
    info = {
        'version': ROSBAG2_METADATA_VERSION,
        'storage_identifier': 'mcap',
        'relative_file_paths': [file_name],
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {'topic_metadata': {
                'name': t['name'],
                'type': t['type'],
                'serialization_format': MESSAGE_ENCODING,
                'offered_qos_profiles': [dict(q) for q in t.get('offered_qos_profiles', [])],
                'type_description_hash': t.get('type_description_hash', ''),
            },
             'message_count': int(t['message_count'])}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'files': [{'path': file_name,
                   'starting_time': {'nanoseconds_since_epoch': start},
                   'duration': {'nanoseconds': duration},
                   'message_count': count}],
        'custom_data': None,
        'ros_distro': ros_distro or os.environ.get('ROS_DISTRO') or 'jazzy',
    }
    return yaml.safe_dump(info, default_flow_style=False, sort_keys=False).strip()


# ----------------------------------------------------------------------------- CDR checks

class CdrError(ValueError):
    """Bytes that are not a CDR message of the channel's type; says where they fail."""


_CDR_SIZES = {'bool': 1, 'byte': 1, 'char': 1, 'int8': 1, 'uint8': 1, 'int16': 2,
              'uint16': 2, 'int32': 4, 'uint32': 4, 'float32': 4, 'int64': 8, 'uint64': 8,
              'float64': 8}
_ARRAY = re.compile(r'^(.*?)\[(<=)?(\d*)\]$')
_ENCAPSULATIONS = {b'\x00\x00': '>', b'\x00\x01': '<'}    # plain CDR, big / little endian
#: trailing bytes a CDR message may carry after its last field (padding to 4 bytes)
MAX_CDR_PADDING = 3


def _definition_sections(type_name: str, definition: str) -> dict:
    """Type name (``pkg/Type``) -> its field lines, from a complete ``ros2msg`` definition."""
    package, _, name = split_type_name(type_name)
    sections = {f'{package}/{name}': []}
    current = sections[f'{package}/{name}']
    for line in definition.splitlines():
        text = line.split('#', 1)[0].strip()
        if not text or set(text) == {'='}:
            continue
        if text.startswith('MSG:'):
            dep_package, _, dep_name = split_type_name(text[4:].strip())
            current = sections.setdefault(f'{dep_package}/{dep_name}', [])
            continue
        current.append(text)
    return sections


def _field_spec(token: str, package: str):
    """(base type, string bound, array kind, count): array kind None, 'fixed' or 'sequence'."""
    kind, count = None, None
    match = _ARRAY.match(token)
    if match:
        token, bounded, digits = match.groups()
        kind = 'fixed' if digits and not bounded else 'sequence'
        count = int(digits) if digits else None
    bound = None
    if token.startswith(('string<=', 'wstring<=')):
        token, bound = token.split('<=')
        bound = int(bound)
    if token not in _CDR_SIZES and token not in ('string', 'wstring'):
        if '/' not in token:
            token = 'std_msgs/Header' if token == 'Header' else f'{package}/{token}'
        dep_package, _, dep_name = split_type_name(token)
        token = f'{dep_package}/{dep_name}'
    return token, bound, kind, count


def cdr_fields(type_name: str, definition: str) -> dict:
    """Type (``pkg/Type``) -> list of (name, base type, string bound, array kind, count) of the
    main type and every type it uses, from its ``ros2msg`` definition (constants left out).
    Raises :class:`CdrError` where the definition lacks a type it uses."""
    sections = _definition_sections(type_name, definition)
    out = {}
    for owner, lines in sections.items():
        package = owner.split('/')[0]
        fields = []
        for text in lines:
            parts = text.split()
            if len(parts) < 2 or '=' in parts[1] or (len(parts) > 2 and parts[2].startswith('=')):
                continue      # a constant (NAME=value)
            try:
                fields.append((parts[1], *_field_spec(parts[0], package)))
            except SchemaError as err:
                raise CdrError(f'{type_name}: {err}') from None
        out[owner] = fields
    for owner, fields in out.items():
        for field in fields:
            if field[1] not in _CDR_SIZES and field[1] not in ('string', 'wstring') \
                    and field[1] not in out:
                raise CdrError(f'{type_name}: the definition lacks {field[1]} (used in {owner})')
    return out


def cdr_checker(type_name: str, definition: str):
    """A function ``check(data)`` that raises :class:`CdrError` unless ``data`` is one whole
    CDR message of the type (``ros2msg`` ``definition``): encapsulation header, every field in
    bounds at its alignment, strings terminated and within their bounds, sequences within
    theirs, and at most :data:`MAX_CDR_PADDING` bytes after the last field."""
    types = cdr_fields(type_name, definition)
    package, _, name = split_type_name(type_name)
    main = f'{package}/{name}'

    def check(data) -> None:
        data = bytes(data)
        order = _ENCAPSULATIONS.get(data[:2])
        if order is None or len(data) < 4:
            raise CdrError(f'{len(data)} bytes that do not start with a plain CDR header')
        end = _walk(types, main, data, 4, order, 4)
        if len(data) - end > MAX_CDR_PADDING:
            raise CdrError(f'{len(data) - 4} bytes of data, a {name} here ends after '
                           f'{end - 4} (the bytes are of another type)')
    return check


def _need(data, position: int, size: int, what: str) -> None:
    if position + size > len(data):
        raise CdrError(f'{what} at byte {position - 4} overruns the {len(data) - 4} bytes '
                       'of data')


def _aligned(position: int, size: int) -> int:
    return 4 + (-(-(position - 4) // size)) * size


def _walk(types: dict, owner: str, data: bytes, position: int, order: str, depth: int) -> int:
    fields = types[owner]
    if not fields:    # an empty message carries one byte
        _need(data, position, 1, owner)
        return position + 1
    for name, base, bound, kind, count in fields:
        what = f'{owner.split("/")[-1]}.{name}'
        if kind is not None and kind != 'fixed':
            position = _aligned(position, 4)
            _need(data, position, 4, what)
            (count_read,) = struct.unpack_from(order + 'I', data, position)
            position += 4
            if count is not None and count_read > count:
                raise CdrError(f'{what} holds {count_read} items, at most {count} allowed')
            items = count_read
        else:
            items = 1 if kind is None else count
        if base in _CDR_SIZES:
            size = _CDR_SIZES[base]
            if items:
                position = _aligned(position, size)
                _need(data, position, size * items, what)
                position += size * items
            continue
        for _ in range(items):
            if base in ('string', 'wstring'):
                position = _aligned(position, 4)
                _need(data, position, 4, what)
                (length,) = struct.unpack_from(order + 'I', data, position)
                position += 4
                width = 4 if base == 'wstring' else 1
                if base == 'string' and length < 1:
                    raise CdrError(f'{what}: a string of length 0 (no terminating NUL)')
                _need(data, position, length * width, what)
                if base == 'string' and data[position + length - 1] != 0:
                    raise CdrError(f'{what}: string not terminated by NUL')
                chars = length - 1 if base == 'string' else length
                if bound is not None and chars > bound:
                    raise CdrError(f'{what}: string of {chars} characters, at most {bound}')
                position += length * width
            else:
                if depth > 50:
                    raise CdrError(f'{what}: types nest too deeply')
                position = _walk(types, base, data, position, order, depth + 1)
    return position


def stamped_values_count(type_name: str, definition: str) -> int | None:
    """N where the type is a ``std_msgs/Header`` followed by N float64 only (PoseStamped 7,
    WrenchStamped 6, Vector3Stamped 3: :func:`decode_stamped` reads them), else None."""
    try:
        types = cdr_fields(type_name, definition)
    except CdrError:
        return None
    package, _, name = split_type_name(type_name)
    fields = types[f'{package}/{name}']
    if not fields or fields[0][1:] != ('std_msgs/Header', None, None, None):
        return None
    header = [f[1:] for f in types.get('std_msgs/Header', [])]
    if header != [('builtin_interfaces/Time', None, None, None), ('string', None, None, None)]:
        return None

    def doubles(owner) -> int | None:
        total = 0
        for _, base, _, kind, count in types[owner]:
            if kind == 'sequence':
                return None
            items = 1 if kind is None else count
            if base == 'float64':
                total += items
            elif base in types:
                inner = doubles(base)
                if inner is None:
                    return None
                total += inner * items
            else:
                return None
        return total

    count = 0
    for _, base, _, kind, items in fields[1:]:
        inner = 1 if base == 'float64' else doubles(base) if base in types else None
        if inner is None or kind == 'sequence':
            return None
        count += inner * (1 if kind is None else items)
    return count


_STAMP_LE, _STAMP_BE = struct.Struct('<iII'), struct.Struct('>iII')


def decode_stamped(data: bytes, count: int, type_name: str = 'message'):
    """(stamp ns, frame id, ``count`` float64 values) of a Header + float64 message's CDR
    bytes, checked as :func:`cdr_checker` checks them; raises :class:`CdrError`."""
    order = _ENCAPSULATIONS.get(data[:2])
    total = len(data)
    if order is None or total < 16:
        raise CdrError(f'{total} bytes that do not start with a plain CDR header and stamp')
    sec, nanosec, length = (_STAMP_LE if order == '<' else _STAMP_BE).unpack_from(data, 4)
    text_end = 16 + length
    if length < 1 or text_end > total or data[text_end - 1] != 0:
        raise CdrError(f'header.frame_id: a string of {length} bytes does not fit the '
                       f'{total - 4} bytes of data, or lacks its NUL')
    try:
        frame_id = data[16:text_end - 1].decode('utf-8')
    except UnicodeDecodeError:
        raise CdrError('header.frame_id is not UTF-8') from None
    start = 4 + ((text_end - 4 + 7) & ~7)
    end = start + 8 * count
    if end > total:
        raise CdrError(f'{total - 4} bytes of data, a {type_name} with this frame_id needs '
                       f'{end - 4}')
    if total - end > MAX_CDR_PADDING:
        raise CdrError(f'{total - 4} bytes of data, a {type_name} with this frame_id ends '
                       f'after {end - 4} (the bytes are of another type)')
    return (sec * 1_000_000_000 + nanosec, frame_id,
            struct.unpack_from(f'{order}{count}d', data, start))


def encode_stamped(stamp_ns: int, frame_id: str, values) -> bytes:
    """CDR bytes (little endian, with the encapsulation header) of a Header + float64 message,
    as a DDS publisher sends them: Vector3Stamped (3 values), WrenchStamped (6), PoseStamped
    (7)."""
    layout, frame = _stamped_layout(frame_id, len(values))
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return layout.pack(b'\x00\x01\x00\x00', sec, nanosec, len(frame), frame, *values)


def decode_stamped_run(datas: Sequence[bytes], count: int,
                       type_name: str = 'message') -> tuple:
    """:func:`decode_stamped` of a run of messages at once, as far as they share one layout:
    (k, stamps (k,) int64 ns, frame id, values (k, ``count``) float64) of the first k messages,
    which are little endian, as long as the first and have its header bytes (encapsulation,
    frame id and padding) - the same checks then pass and the same fields come out. k = 0
    where the first is not such a message (decode it alone: :func:`decode_stamped` says why)."""
    if not datas or datas[0][:2] != b'\x00\x01':
        return 0, None, '', None
    first = datas[0]
    try:
        _, frame_id, _ = decode_stamped(first, count, type_name)
    except CdrError:
        return 0, None, '', None
    size = len(first)
    start = 4 + ((12 + len(frame_id.encode('utf-8')) + 1 + 7) & ~7)   # as decode_stamped
    k = len(datas)
    joined = b''.join(datas)
    if len(joined) != k * size:         # another length among them: the run of the first's
        k = next(i for i, data in enumerate(datas) if len(data) != size)
        joined = joined[:k * size]
    raw = np.frombuffer(joined, np.uint8).reshape(k, size)
    same = ((raw[:, :4] == raw[0, :4]).all(axis=1)
            & (raw[:, 12:start] == raw[0, 12:start]).all(axis=1))
    if not same.all():
        k = int(same.argmin())
    fields = np.frombuffer(joined, _run_dtype(size, start, count), count=k)
    stamps = fields['sec'].astype(np.int64) * 1_000_000_000 + fields['nanosec']
    return k, stamps, frame_id, fields['values'].astype(float)


def encode_stamped_run(stamps_ns: np.ndarray, frame_id: str, values: np.ndarray) -> list:
    """:func:`encode_stamped` of a run of messages (stamps (k,) ns, values (k, count)): the
    same bytes, one array pass."""
    values = np.asarray(values, dtype=float)
    layout, frame = _stamped_layout(frame_id, values.shape[1])
    size = layout.size
    start = size - 8 * values.shape[1]
    out = np.zeros(len(values), _run_dtype(size, start, values.shape[1]))
    raw = out.view(np.uint8).reshape(len(values), size)
    raw[:, :4] = (0, 1, 0, 0)
    raw[:, 12:start] = np.frombuffer(struct.pack('<I', len(frame)) + frame
                                     + bytes(start - 16 - len(frame)), np.uint8)
    sec, nanosec = np.divmod(np.asarray(stamps_ns, dtype=np.int64), 1_000_000_000)
    out['sec'], out['nanosec'], out['values'] = sec, nanosec, values
    buffer = out.tobytes()
    return [buffer[i:i + size] for i in range(0, len(buffer), size)]


@lru_cache(maxsize=64)
def _run_dtype(size: int, start: int, count: int) -> np.dtype:
    """A record of a Header + ``count`` float64 message of ``size`` bytes whose values
    start at byte ``start`` (little endian): the stamp's fields and the values."""
    return np.dtype({'names': ['sec', 'nanosec', 'values'],
                     'formats': ['<i4', '<u4', ('<f8', (count,))],
                     'offsets': [4, 8, start], 'itemsize': size})


@lru_cache(maxsize=64)
def _stamped_layout(frame_id: str, count: int) -> tuple:
    """The struct of a Header + ``count`` float64 message with this frame id, and the frame
    id's bytes with their NUL (zero padding to the doubles' alignment comes with the struct)."""
    frame = frame_id.encode('utf-8') + b'\0'
    padded = len(frame) + (-(12 + len(frame)) % 8)
    return struct.Struct(f'<4siII{padded}s{count}d'), frame

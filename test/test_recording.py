"""MCAP recording: cdpr_record as a process, files read back by independent readers.

Every ROS process runs as a subprocess with a domain id of its own (fixture ``ros_env``); the
recordings land in ``test_output/test_recording/<test>/``, kept when a test fails.
Figures (throughput, bytes per message, what a SIGKILL lost) are printed: ``pytest -s``.
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader, NonSeekingReader
from mcap.writer import CompressionType, Writer
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosReliability
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

from cdpr_dynamics.recording.base import RecordingError
from cdpr_dynamics.recording.reader import read_messages, recording_info
from cdpr_dynamics.recording.recovery import recover_recording
from cdpr_dynamics.recording.writer import ChunkedFile, FIRST_CHUNK_BYTES
from msg_adapters import mcap_schema
from conftest import wait_until
from processes import counts_so_far, finish, Processes

PYTHON = sys.executable
N_PER_TOPIC = 20
EVENT_TOPIC = '/frequency_response/_service_event'
EVENT_TYPE = 'rcl_interfaces/srv/GetParameters_Event'
TYPES = {
    '/pose': 'geometry_msgs/msg/PoseStamped',
    '/wrench': 'geometry_msgs/msg/WrenchStamped',
    '/predicted_displacement': 'geometry_msgs/msg/Vector3Stamped',
    '/cable_tensions': 'sensor_msgs/msg/JointState',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
}

# A node that publishes known messages on the node's topics and serves frequency_response with
# service introspection, so the recorder has every kind of traffic it must record.
PUBLISHER = r'''
import json, os, sys, time
import rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_services_default
from rclpy.service_introspection import ServiceIntrospectionState
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import ParameterValue
from rcl_interfaces.srv import GetParameters
from sensor_msgs.msg import JointState

mode, out = sys.argv[1], sys.argv[2]
rclpy.init()
node = Node('fake_cdpr')


def wait(condition, timeout, what):
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            sys.exit('publisher: timed out waiting for ' + what)
        rclpy.spin_once(node, timeout_sec=0.05)


def report(data):
    with open(out + '.tmp', 'w') as f:
        json.dump(data, f)
    os.replace(out + '.tmp', out)   # the test sees the whole file or none


def stamp(msg, i):
    msg.header.stamp.sec = 1000 + i
    msg.header.stamp.nanosec = 1000 * i
    msg.header.frame_id = 'world'
    return msg


if mode == 'known':
    n = int(sys.argv[3])
    pubs = {name: node.create_publisher(cls, name, 100) for name, cls in (
        ('pose', PoseStamped), ('wrench', WrenchStamped),
        ('predicted_displacement', Vector3Stamped), ('cable_tensions', JointState),
        ('/diagnostics', DiagnosticArray))}

    def frf(request, response):
        response.values = [ParameterValue(type=8, double_array_value=[1.0, 2.0, 3.0])
                           for _ in request.names]
        return response

    service = node.create_service(GetParameters, 'frequency_response', frf)
    service.configure_introspection(node.get_clock(), qos_profile_services_default,
                                    ServiceIntrospectionState.CONTENTS)
    wait(lambda: all(p.get_subscription_count() > 0 for p in pubs.values())
         and node.count_subscribers('/frequency_response/_service_event') > 0,
         30.0, 'the recorder to subscribe')
    for i in range(n):
        m = stamp(PoseStamped(), i)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = 0.001 * i, -0.002 * i, 1.25
        m.pose.orientation.w = 1.0
        pubs['pose'].publish(m)
        m = stamp(WrenchStamped(), i)
        m.wrench.force.z = 1500.0 + i
        m.wrench.torque.x = 0.5 * i
        pubs['wrench'].publish(m)
        m = stamp(Vector3Stamped(), i)
        m.vector.x, m.vector.z = 1e-6 * i, -2e-6 * i
        pubs['predicted_displacement'].publish(m)
        m = stamp(JointState(), i)
        m.name = ['cable_%d' % k for k in range(8)]
        m.position = [1.5 + 0.01 * k for k in range(8)]
        m.effort = [100.0 + i + k for k in range(8)]
        pubs['cable_tensions'].publish(m)
        m = DiagnosticArray()
        m.header.stamp.sec, m.header.stamp.nanosec = 1000 + i, 1000 * i
        m.status = [DiagnosticStatus(level=DiagnosticStatus.WARN, name='cdpr_dynamics',
                                     message='step %d' % i, hardware_id='sim',
                                     values=[KeyValue(key='i', value=str(i))])]
        pubs['/diagnostics'].publish(m)
        time.sleep(0.002)   # pacing, not synchronisation
    client = node.create_client(GetParameters, 'frequency_response')
    wait(client.service_is_ready, 10.0, 'the service')
    future = client.call_async(GetParameters.Request(names=['frequency_hz']))
    wait(future.done, 10.0, 'the service response')
    report({'published': n, 'response': list(future.result().values[0].double_array_value)})
    sys.stdin.read()   # keep the writers alive until the test is done

elif mode in ('steady', 'flood'):
    rate, duration = float(sys.argv[3]), float(sys.argv[4])
    pub = node.create_publisher(PoseStamped, 'pose', 100)
    wait(lambda: pub.get_subscription_count() > 0, 30.0, 'the recorder to subscribe')
    stamps = []
    msg = PoseStamped()
    t0 = time.monotonic()
    with open(out + '.started.tmp', 'w') as f:
        f.write(str(time.time_ns()))
    os.replace(out + '.started.tmp', out + '.started')
    i = 0
    while True:
        now = time.monotonic()
        if now - t0 >= duration:
            break
        if mode == 'steady':
            target = t0 + i / rate
            if now < target:
                time.sleep(target - now)
        ns = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 10**9)
        msg.pose.position.x = float(i)
        pub.publish(msg)
        if mode == 'steady':
            stamps.append(ns)
        i += 1
    report({'published': i, 'seconds': time.monotonic() - t0, 'stamps': stamps})
    sys.stdin.read()
'''


# ----------------------------------------------------------------------------- helpers


class RecordingProcesses(Processes):
    """The recorder and the fake node of these tests."""

    def recorder(self, path: Path, *extra, **popen) -> subprocess.Popen:
        return self.start('cdpr_record', [PYTHON, '-m', 'cdpr_dynamics.cli.record',
                                          '--output', str(path), *extra], **popen)

    def publisher(self, *args) -> subprocess.Popen:
        script = self.folder / 'fake_cdpr.py'
        script.write_text(PUBLISHER)
        return self.start('publisher', [PYTHON, str(script), *args], stdin=subprocess.PIPE)


@pytest.fixture
def procs(ros_env, output_dir):
    p = RecordingProcesses(ros_env, output_dir)
    yield p
    p.stop_all()


def expected_fields(topic: str, i: int) -> dict:
    """What the fake node published as message i on a topic (attribute path -> value)."""
    stamp = {'header.stamp.sec': 1000 + i, 'header.stamp.nanosec': 1000 * i}
    if topic == '/pose':
        return {**stamp, 'header.frame_id': 'world', 'pose.position.x': 0.001 * i,
                'pose.position.y': -0.002 * i, 'pose.position.z': 1.25,
                'pose.orientation.w': 1.0}
    if topic == '/wrench':
        return {**stamp, 'wrench.force.z': 1500.0 + i, 'wrench.torque.x': 0.5 * i}
    if topic == '/predicted_displacement':
        return {**stamp, 'vector.x': 1e-6 * i, 'vector.z': -2e-6 * i}
    if topic == '/cable_tensions':
        return {**stamp, 'name': [f'cable_{k}' for k in range(8)],
                'position': [1.5 + 0.01 * k for k in range(8)],
                'effort': [100.0 + i + k for k in range(8)]}
    if topic == '/diagnostics':
        return {**stamp, 'status.0.name': 'cdpr_dynamics', 'status.0.message': f'step {i}',
                'status.0.hardware_id': 'sim', 'status.0.values.0.key': 'i',
                'status.0.values.0.value': str(i)}
    raise KeyError(topic)


def field(msg, dotted: str):
    for part in dotted.split('.'):
        msg = msg[int(part)] if part.isdigit() else getattr(msg, part)
    return msg


def check_fields(topic: str, i: int, msg, reader: str):
    for path, want in expected_fields(topic, i).items():
        have = field(msg, path)
        if isinstance(want, list):
            have = list(have)
            if want and isinstance(want[0], float):
                assert have == pytest.approx(want), (reader, topic, i, path)
                continue
        if isinstance(want, float):
            assert have == pytest.approx(want, rel=1e-12, abs=1e-15), (reader, topic, i, path)
        else:
            assert have == want, (reader, topic, i, path, have)


def index_of(topic: str, msg) -> int:
    return int(field(msg, 'header.stamp.sec')) - 1000


def rosbags_read(path: Path) -> tuple[dict, dict]:
    """Every message of a file through rosbags: topic -> list of (log time, message)."""
    out, types = {}, {}
    with AnyReader([path]) as reader:
        # rosbags' type system has no 'srv' namespace: it files pkg/srv/X as pkg/srv/msg/X.
        for conn in reader.connections:
            if '/srv/' in conn.msgtype and conn.msgtype not in reader.typestore.fielddefs:
                mangled = conn.msgtype.replace('/srv/', '/srv/msg/')
                reader.typestore.register({conn.msgtype: reader.typestore.fielddefs[mangled]})
        for conn in reader.connections:
            types[conn.topic] = (conn.msgtype, conn.msgcount,
                                 conn.ext.serialization_format, conn.ext.offered_qos_profiles)
        for conn, timestamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append(
                (timestamp, reader.deserialize(raw, conn.msgtype)))
    return out, types


# ----------------------------------------------------------------------------- schemas (no ROS)


@pytest.mark.parametrize('type_name', [*TYPES.values(), 'std_msgs/msg/Header'])
def test_definition_hashes_to_the_installed_type_hash(type_name):
    """The concatenated definition, parsed by rosbags, gives the RIHS01 hash of the wheels."""
    text = mcap_schema.message_definition(type_name)
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(text, type_name))
    assert mcap_schema.type_hash(type_name).startswith('RIHS01_')
    assert store.hash_rihs01(type_name) == mcap_schema.type_hash(type_name)


def test_definition_layout_is_rosbag2s():
    text = mcap_schema.message_definition('geometry_msgs/msg/PoseStamped')
    share = Path(mcap_schema.share_directory('geometry_msgs'))
    assert text.startswith((share / 'msg' / 'PoseStamped.msg').read_text())
    sections = text.split('\n' + '=' * 80 + '\n')
    # dependencies sorted by the name written in the field, depth first, each once
    assert [s.splitlines()[0] for s in sections[1:]] == [
        'MSG: geometry_msgs/Pose', 'MSG: geometry_msgs/Point', 'MSG: geometry_msgs/Quaternion',
        'MSG: std_msgs/Header', 'MSG: builtin_interfaces/Time']
    event = mcap_schema.message_definition(EVENT_TYPE)
    assert event.splitlines()[:3] == [
        'service_msgs/ServiceEventInfo info',
        'rcl_interfaces/GetParameters_Request[<=1] request',
        'rcl_interfaces/GetParameters_Response[<=1] response']
    assert 'MSG: rcl_interfaces/ParameterValue' in event
    assert mcap_schema.type_hash(EVENT_TYPE).startswith('RIHS01_')
    with pytest.raises(mcap_schema.SchemaError, match='no_such_pkg'):
        mcap_schema.message_definition('no_such_pkg/msg/Nothing')


def test_offered_qos_profiles_yaml_is_rosbag2_jazzys():
    from rclpy.qos import QoSProfile, DurabilityPolicy, ReliabilityPolicy
    profile = QoSProfile(depth=7, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    text = mcap_schema.offered_qos_profiles_yaml([profile])
    assert text == '\n'.join([
        '- history: keep_last', '  depth: 7', '  reliability: best_effort',
        '  durability: transient_local', '  deadline:', '    sec: 0', '    nsec: 0',
        '  lifespan:', '    sec: 0', '    nsec: 0', '  liveliness: system_default',
        '  liveliness_lease_duration:', '    sec: 0', '    nsec: 0',
        '  avoid_ros_namespace_conventions: false'])
    assert mcap_schema.offered_qos_profiles_yaml([]) == '[]'
    (parsed,) = parse_qos(text)
    assert parsed.depth == 7 and parsed.reliability == QosReliability.BEST_EFFORT


# ----------------------------------------------------------------------------- SIGINT / SIGTERM


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_record_and_read_back_with_independent_readers(procs, output_dir, sig):
    path = output_dir / 'traffic.mcap'
    recorder = procs.recorder(path)
    done = output_dir / 'published.json'
    procs.publisher('known', done, N_PER_TOPIC)
    wait_until(done.exists, 60, 'the fake node to publish')
    want = {**{t: N_PER_TOPIC for t in TYPES}, EVENT_TOPIC: 2}
    wait_until(lambda: counts_so_far(path) == want, 20,
               f'the recording to hold {want} (has {counts_so_far(path)})')
    out = finish(recorder, sig)
    total = sum(want.values())
    assert f'wrote {total} messages' in out and str(path.resolve()) in out, out

    # --- the file: profile, schemas, channels, summary and index (mcap) ---
    with open(path, 'rb') as stream:
        reader = make_reader(stream)
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == 'ros2' and header.library
        assert summary.statistics.message_count == total
        assert summary.chunk_indexes
        assert summary.statistics.chunk_count == len(summary.chunk_indexes)
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)  # indexed
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {*TYPES.values(), EVENT_TYPE}
        for name, schema in schemas.items():
            assert schema.encoding == 'ros2msg'
            assert schema.data.decode() == mcap_schema.message_definition(name)
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == set(want)
        for topic, channel in channels.items():
            type_name = summary.schemas[channel.schema_id].name
            assert channel.message_encoding == 'cdr'
            assert set(channel.metadata) == {'offered_qos_profiles', 'topic_type_hash'}
            assert channel.metadata['topic_type_hash'] == mcap_schema.type_hash(type_name)
            qos = parse_qos(channel.metadata['offered_qos_profiles'])
            assert qos and all(q.reliability == QosReliability.RELIABLE for q in qos), topic
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        bag = yaml.safe_load(meta['rosbag2']['serialized_metadata'])
        assert bag['version'] == 9 and bag['message_count'] == total
        assert {t['topic_metadata']['name']: t['message_count']
                for t in bag['topics_with_message_count']} == want

    # --- mcap + mcap-ros2-support: decode every message (it rejects the event type's name) ---
    seen = {}
    with open(path, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            assert message.publish_time <= message.log_time
            if channel.topic == EVENT_TOPIC:
                continue
            decoded = DecoderFactory().decoder_for('cdr', schema)(message.data)
            check_fields(channel.topic, index_of(channel.topic, decoded), decoded, 'mcap_ros2')
    assert seen == want

    # --- rosbags: types, counts, QoS, every message decoded ---
    by_topic, types = rosbags_read(path)
    assert {t: (v[0], v[1], v[2]) for t, v in types.items()} == {
        **{t: (TYPES[t], N_PER_TOPIC, 'cdr') for t in TYPES}, EVENT_TOPIC: (EVENT_TYPE, 2, 'cdr')}
    for topic in TYPES:
        msgs = by_topic[topic]
        assert [index_of(topic, m) for _, m in msgs] == list(range(N_PER_TOPIC))
        for i, (_, m) in enumerate(msgs):
            check_fields(topic, i, m, 'rosbags')
    events = [m for _, m in by_topic[EVENT_TOPIC]]
    assert [e.info.event_type for e in events] == [1, 2]  # REQUEST_RECEIVED, RESPONSE_SENT
    assert list(events[0].request[0].names) == ['frequency_hz']
    assert list(events[1].response[0].values[0].double_array_value) == [1.0, 2.0, 3.0]

    # --- read_messages (rclpy classes): same content, log-time order ---
    got = list(read_messages(path))
    assert len(got) == total
    assert [m.log_time_ns for m in got] == sorted(m.log_time_ns for m in got)
    for topic in TYPES:
        mine = [m for m in got if m.topic == topic]
        assert {m.type for m in mine} == {TYPES[topic]}
        for i, m in enumerate(mine):
            check_fields(topic, i, m.message, 'read_messages')
    events = [m.message for m in got if m.topic == EVENT_TOPIC]
    assert list(events[1].response[0].values[0].double_array_value) == [1.0, 2.0, 3.0]
    only = list(read_messages(path, {'pose': 'geometry_msgs/msg/PoseStamped'}))
    assert len(only) == N_PER_TOPIC and {m.topic for m in only} == {'/pose'}


# ----------------------------------------------------------------------------- SIGKILL


def test_sigkill_loses_at_most_the_last_second(procs, output_dir):
    rate, run_s = 200.0, 3.0
    path = output_dir / 'killed.mcap'
    recorder = procs.recorder(path)
    done = output_dir / 'steady.json'
    publisher = procs.publisher('steady', done, rate, run_s + 3.0)
    started = Path(str(done) + '.started')
    wait_until(started.exists, 60, 'the publisher to start')
    t_start = int(started.read_text()) / 1e9
    time.sleep(max(0.0, t_start + run_s - time.time()))   # the experiment: record for run_s
    killed_at = time.time_ns()
    recorder.send_signal(signal.SIGKILL)
    recorder.wait(timeout=10)
    publisher.stdin.close()
    wait_until(done.exists, 30, 'the publisher to finish')
    sent = sum(1 for s in json.loads(done.read_text())['stamps'] if s < killed_at)

    with pytest.raises(RecordingError, match='incomplete'):
        next(read_messages(path))
    survivors = list(read_messages(path, allow_incomplete=True))
    xs = [int(m.message.pose.position.x) for m in survivors]
    assert xs == list(range(len(xs))), 'what survives is the start of the stream, no gaps'
    lost = sent - len(xs)
    lost_s = (killed_at - survivors[-1].log_time_ns) / 1e9
    size = path.stat().st_size
    info = recording_info(path)
    print(f'\nSIGKILL after {run_s} s at {rate:.0f} msg/s: {sent} sent before the kill, '
          f'{len(xs)} survived in {info.chunk_count} chunks ({size} bytes), {lost} lost '
          f'= the last {lost_s:.2f} s')
    assert not info.complete and info.topics['/pose'].message_count == len(xs)
    assert len(xs) >= rate * (run_s - 1.5)
    assert lost <= rate * 1.3, 'at most ~1 s (chunk interval) plus the 0.1 s check period'

    # mcap's own streaming reader reads the same messages up to the cut
    count = 0
    with open(path, 'rb') as stream:
        try:
            for _ in NonSeekingReader(stream).iter_messages(log_time_order=False):
                count += 1
        except EndOfFile:
            pass
    assert count == len(xs)
    # rosbags needs the footer; the recovered copy is complete and reads everywhere
    with pytest.raises(Exception):
        rosbags_read(path)
    fixed = output_dir / 'recovered.mcap'
    with pytest.raises(RecordingError, match='is the recording to recover'):
        recover_recording(path, path, force=True)     # would have emptied the recording
    assert recover_recording(path, fixed) == len(xs)
    with pytest.raises(RecordingError, match='exists; not overwriting it'):
        recover_recording(path, fixed)
    assert not list(output_dir.glob('.*partial*'))
    by_topic, _ = rosbags_read(fixed)
    assert [int(m.pose.position.x) for _, m in by_topic['/pose']] == xs
    assert recording_info(fixed).complete


# ----------------------------------------------------------------------------- throughput


def test_throughput_with_a_flooding_publisher(procs, output_dir):
    """A publisher as fast as it can go: the recorder keeps up without a crash, ends cleanly
    on SIGINT with a finished file, and what it kept are distinct messages of the publisher,
    in the order sent. The rate is printed here and measured by cdpr_bench (timings belong in
    benchmarks)."""
    path = output_dir / 'flood.mcap'
    recorder = procs.recorder(path, '--topics', 'pose')
    done = output_dir / 'flood.json'
    procs.publisher('flood', done, 0, 2.0)
    wait_until(done.exists, 60, 'the publisher to finish')
    published = json.loads(done.read_text())
    wait_until(lambda: counts_so_far(path).get('/pose', 0) > 0, 10, 'recorded messages')
    finish(recorder, signal.SIGINT)
    info = recording_info(path)
    n = info.message_count
    rate = n / max(1e-9, (info.end_ns - info.start_ns) / 1e9)
    per_message = path.stat().st_size / n
    print(f'\nthroughput: publisher sent {published["published"]} PoseStamped in '
          f'{published["seconds"]:.1f} s ({published["published"] / published["seconds"]:.0f}/s); '
          f'recorded {n} at {rate:.0f} msg/s, {per_message:.0f} bytes/message in the file '
          f'(2 cores shared by both processes)')
    xs = [int(m.message.pose.position.x) for m in read_messages(path)]
    assert len(xs) == n > 0
    assert all(a < b for a, b in zip(xs, xs[1:])), 'a message twice or out of order'
    assert 0 <= xs[0] and xs[-1] < published['published']


# ----------------------------------------------------------------------------- bad files (no ROS)


def write_sample(path: Path, n: int = 50) -> None:
    """A small file with the recorder's conventions, written without ROS."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    with open(path, 'wb') as stream:
        writer = Writer(stream, chunk_size=1024, compression=CompressionType.NONE)
        writer.start(profile='ros2', library='test')
        type_name = 'geometry_msgs/msg/PoseStamped'
        schema = writer.register_schema(type_name, 'ros2msg',
                                        mcap_schema.message_definition(type_name).encode())
        channel = writer.register_channel('/pose', 'cdr', schema,
                                          mcap_schema.channel_metadata(type_name))
        for i in range(n):
            msg = PoseStamped()
            msg.header.stamp.sec = 1000 + i
            msg.pose.position.x = 0.001 * i
            writer.add_message(channel, 10**9 + i, serialize_message(msg), 10**9 + i)
        writer.finish()


def test_bad_files_give_one_line_errors(tmp_path):
    good = tmp_path / 'good.mcap'
    write_sample(good)
    assert len(list(read_messages(good))) == 50
    data = good.read_bytes()

    def error(path, **kwargs) -> str:
        with pytest.raises(RecordingError) as caught:
            list(read_messages(path, **kwargs))
        text = str(caught.value)
        assert '\n' not in text and str(path) in text
        return text

    truncated = tmp_path / 'truncated.mcap'
    truncated.write_bytes(data[:len(data) // 2])
    assert 'incomplete' in error(truncated)
    survivors = list(read_messages(truncated, allow_incomplete=True))
    assert 0 < len(survivors) < 50
    garbage = tmp_path / 'garbage.mcap'
    garbage.write_bytes(os.urandom(4096))
    assert 'not an MCAP file' in error(garbage)
    empty = tmp_path / 'empty.mcap'
    empty.write_bytes(b'')
    assert 'empty' in error(empty)
    assert 'no such file' in error(tmp_path / 'missing.mcap')
    assert 'no topic /wrench' in error(good, topics=['wrench'])
    assert 'has type geometry_msgs/msg/PoseStamped, expected' in error(
        good, topics={'/pose': 'geometry_msgs/msg/WrenchStamped'})
    # a flipped byte inside a chunk: the chunk CRC catches it
    corrupt = tmp_path / 'corrupt.mcap'
    raw = bytearray(data)
    at = data.index(b'\x00' * 8, 600)   # inside the first chunk's message data
    raw[at] ^= 0xFF
    corrupt.write_bytes(bytes(raw))
    assert 'corrupt' in error(corrupt)
    # a cut mid-file, then garbage where the rest was
    mangled = tmp_path / 'mangled.mcap'
    mangled.write_bytes(data[:len(data) // 2] + os.urandom(len(data) // 2))
    assert error(mangled)


CLOSE_KEEPS_WAITING = """
import sys, time
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.qos import QoSProfile
from cdpr_dynamics.recording.recorder import Recorder
rclpy.init()
node = rclpy.create_node('close_drain_recorder')
source = rclpy.create_node('close_drain_source')
publisher = source.create_publisher(PoseStamped, 'pose', QoSProfile(depth=1000))
recorder = Recorder(node, sys.argv[1], ['pose'], force=True)
deadline = time.monotonic() + 30.0
while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
    recorder.poll()          # discovery only: nothing is published yet
    time.sleep(0.05)         # the period of that poll, not a synchronisation
for i in range(700):
    msg = PoseStamped()
    msg.pose.position.x = float(i)
    publisher.publish(msg)
assert publisher.wait_for_all_acked(Duration(seconds=30.0))   # all in the reader's queue
summary = recorder.close()   # never spun: every message still waits on the subscription
print(summary.topics)
"""


def test_close_writes_what_waits_on_the_subscriptions(ros_env, tmp_path):
    """Stopping a recorder whose subscriptions still hold messages (it lagged: a busy machine,
    a flood) writes them before the file is finished; nothing delivered is dropped."""
    path = tmp_path / 'drain.mcap'
    result = subprocess.run([PYTHON, '-c', CLOSE_KEEPS_WAITING, str(path)], env=ros_env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    by_topic, _ = rosbags_read(path)
    xs = [int(m.pose.position.x) for _, m in by_topic['/pose']]
    assert xs == list(range(700))


def test_cli_refuses_to_overwrite(ros_env, tmp_path):
    target = tmp_path / 'precious.mcap'
    target.write_bytes(b'what the user recorded')
    result = subprocess.run(
        [PYTHON, '-m', 'cdpr_dynamics.cli.record', '--output', str(target)],
        env=ros_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert result.stderr.strip().count('\n') == 0 and 'exists' in result.stderr
    assert 'Traceback' not in result.stderr
    assert target.read_bytes() == b'what the user recorded'


# ----------------------------------------------------------------------------- full disk


def write_failure_checks(path: Path, err: str, cause: str) -> int:
    """What a recorder stopped by a failing write must leave: one error line naming the cause,
    and a file every reader opens, with the same messages in the order published (a flood:
    the subscription's queue may drop some). A publisher that starts before the recorder has
    subscribed is told of in a warning of its own (its first messages are not in the file)."""
    lines = [line for line in err.strip().splitlines()
             if not (line.startswith('[WARN]') and 'came before the recorder subscribed' in line)]
    assert len(lines) == 1 and 'Traceback' not in err, err
    assert lines[0].startswith('cdpr_record: error: cannot write') and cause in lines[0], err
    assert 'finished with its summary' in lines[0], err
    with open(path, 'rb') as stream:                       # mcap: summary, footer, index
        reader = make_reader(stream)
        summary = reader.get_summary()
        n = summary.statistics.message_count
        assert n == sum(1 for _ in reader.iter_messages())
    assert f'the file keeps {n} messages' in lines[0], err
    by_topic, _ = rosbags_read(path)                       # rosbags needs the footer
    xs = [int(m.pose.position.x) for _, m in by_topic['/pose']]
    assert len(xs) == n and xs == sorted(set(xs)), 'in the order published, each once'
    info = recording_info(path)
    assert info.complete and info.message_count == n
    return n


@pytest.fixture
def small_disk(output_dir):
    """A 192 kB tmpfs (we run as root here); what it holds is copied out before unmounting."""
    mount = output_dir / 'small_disk'
    mount.mkdir()
    done = subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=192k', 'tmpfs', str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f'cannot mount a tmpfs here ({done.stderr.strip()}); '
                    'test_file_size_limit_leaves_a_finished_file covers a failing write')
    try:
        yield mount
    finally:
        for item in mount.iterdir():
            shutil.copy(item, output_dir / item.name)
        if subprocess.run(['umount', str(mount)]).returncode != 0:
            subprocess.run(['umount', '--lazy', str(mount)], check=True)   # a file still open


def test_full_disk_leaves_a_finished_file(procs, output_dir, small_disk):
    path = small_disk / 'full.mcap'
    recorder = procs.recorder(path, '--topics', 'pose')
    procs.publisher('flood', output_dir / 'flood.json', 0, 30.0)
    recorder.wait(timeout=60)          # it stops by itself when the disk is full
    err = recorder.logs[1].read_text()
    assert recorder.returncode == 1, err
    n = write_failure_checks(path, err, 'No space left on device')
    free = shutil.disk_usage(small_disk).free
    print(f'\nfull disk (192 kB tmpfs): kept {n} PoseStamped in {path.stat().st_size} bytes, '
          f'{free} bytes left free')
    assert n > 500
    assert not [p for p in small_disk.iterdir() if p != path], 'no reserve or temporary file'


def test_no_room_even_to_finish_leaves_the_whole_chunks(small_disk, tmp_path):
    """If the freed space is taken before the summary is written (here: the reserve is given
    up and another file fills the disk), the file stays cut after its last whole chunk."""
    path = small_disk / 'cut.mcap'
    out = ChunkedFile(path)
    for topic, type_name in {**TYPES, EVENT_TOPIC: EVENT_TYPE}.items():   # a summary > a page
        schema = out.register_schema(type_name, 'ros2msg',
                                     mcap_schema.message_definition(type_name).encode())
        channel = out.register_channel(topic, 'cdr', schema,
                                       mcap_schema.channel_metadata(type_name))
        if topic == '/pose':
            pose_channel = channel
    channel = pose_channel
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    accepted = 0
    while True:
        msg = PoseStamped()
        msg.pose.position.x = float(accepted)
        if not out.add_message(channel, 10**9 + accepted, serialize_message(msg),
                               10**9 + accepted, accepted):
            break
        accepted += 1
    assert 'No space left on device' in out.error and 0 < out.message_count < accepted
    out._reserve.close()       # the reserve given up, its room taken by another file
    out._reserve = None
    filler = os.open(small_disk / 'filler', os.O_WRONLY | os.O_CREAT)
    try:
        with pytest.raises(OSError, match='No space left'):
            while True:
                os.write(filler, bytes(512))
    finally:
        os.close(filler)
    out.finish()
    assert not out.complete and path.stat().st_size == out.bytes
    count = 0
    with open(path, 'rb') as stream:           # mcap's stream reader: every whole chunk
        try:
            for _ in NonSeekingReader(stream).iter_messages(log_time_order=False):
                count += 1
        except EndOfFile:
            pass
    assert count == out.message_count
    fixed = tmp_path / 'fixed.mcap'
    assert recover_recording(path, fixed) == count
    by_topic, _ = rosbags_read(fixed)
    assert [int(m.pose.position.x) for _, m in by_topic['/pose']] == list(range(count))
    (small_disk / 'filler').unlink()


def test_file_size_limit_leaves_a_finished_file(procs, output_dir):
    """ulimit -f 160 kB: the recorder keeps the first chunks, finished, below the limit."""
    limit = 160_000
    path = output_dir / 'limited.mcap'
    recorder = procs.recorder(path, '--topics', 'pose', preexec_fn=lambda: resource.setrlimit(
        resource.RLIMIT_FSIZE, (limit, limit)))
    procs.publisher('flood', output_dir / 'flood.json', 0, 30.0)
    recorder.wait(timeout=60)
    err = recorder.logs[1].read_text()
    assert recorder.returncode == 1, err
    n = write_failure_checks(path, err, 'File too large')
    print(f'\nfile-size limit {limit} bytes: kept {n} PoseStamped in {path.stat().st_size} '
          'bytes')
    assert path.stat().st_size <= limit and n > 500


def test_chunks_start_small_and_double(tmp_path):
    """The first chunk is bounded (a nearly full disk keeps the first messages); each next
    one may be twice as large, up to the chunk size."""
    path = tmp_path / 'chunks.mcap'
    chunk_size = 100_000
    out = ChunkedFile(path, chunk_size=chunk_size)
    type_name = 'geometry_msgs/msg/PoseStamped'
    schema = out.register_schema(type_name, 'ros2msg',
                                 mcap_schema.message_definition(type_name).encode())
    channel = out.register_channel('/pose', 'cdr', schema,
                                   mcap_schema.channel_metadata(type_name))
    payload = 200
    for i in range(3000):
        assert out.add_message(channel, 10**9 + i, bytes(payload), 10**9 + i, i)
    out.finish()
    assert out.complete and out.error is None
    with open(path, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    sizes = [c.uncompressed_size for c in summary.chunk_indexes]
    record = payload + 31          # a message record: opcode, length, ids and times, data
    bound = FIRST_CHUNK_BYTES
    for size in sizes[:-1]:        # the last one is what remained at finish()
        assert bound <= size < bound + record + 4096, (sizes, bound)   # 4096: the schema
        bound = min(2 * bound, chunk_size)
    assert sum(1 for _ in make_reader(open(path, 'rb')).iter_messages()) == 3000


def record_cli(env, *args) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, '-m', 'cdpr_dynamics.cli.record', *map(str, args)],
                          env=env, capture_output=True, text=True, timeout=60)


def test_recover_cli(ros_env, tmp_path):
    good = tmp_path / 'good.mcap'
    write_sample(good, 200)
    cut = tmp_path / 'cut.mcap'
    data = good.read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    survivors = len(list(read_messages(cut, allow_incomplete=True)))
    assert 0 < survivors < 200
    out = tmp_path / 'recovered.mcap'
    result = record_cli(ros_env, '--recover', cut, out)
    assert result.returncode == 0, result.stderr
    line = result.stdout.strip()
    assert line.count('\n') == 0 and f'recovered {survivors} messages from ' in line, line
    assert f'from {recording_info(cut).chunk_count} whole chunks' in line, line
    assert f'was cut short) into {out.resolve()}: /pose {survivors}' in line, line
    by_topic, _ = rosbags_read(out)
    assert len(by_topic['/pose']) == survivors and recording_info(out).complete
    before = cut.read_bytes()

    def error(*args) -> str:
        result = record_cli(ros_env, '--recover', *args)
        err = result.stderr.strip()
        assert result.returncode == 1 and err.count('\n') == 0 and 'Traceback' not in err, err
        return err

    assert 'exists; not overwriting it' in error(cut, out)
    assert 'is the recording to recover' in error(cut, cut)
    assert '--recover never replaces a file' in error(cut, out, '--force')
    assert 'no such file' in error(tmp_path / 'missing.mcap', tmp_path / 'x.mcap')
    garbage = tmp_path / 'garbage.mcap'
    garbage.write_bytes(os.urandom(3000))
    assert 'not an MCAP file' in error(garbage, tmp_path / 'y.mcap')
    assert cut.read_bytes() == before
    assert not (tmp_path / 'x.mcap').exists() and not (tmp_path / 'y.mcap').exists()
    assert not list(tmp_path.glob('.*partial*'))


def test_messages_published_before_the_recorder_subscribed_are_warned_by_topic(
        ros_context, tmp_path):
    """A pose sent once before the recorder subscribed never reaches the file (volatile
    publisher); the replay would then start from another pose without a word. Closing warns,
    naming the topic: no message at all on /pose, the first two of /wrench missing (its
    publisher's sequence numbers), nothing on /cable_tensions (all recorded)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from cdpr_dynamics.recording.recorder import Recorder
    from cdpr_dynamics.ros.process import wait_until

    talker = rclpy.create_node('talker', context=ros_context)
    quiet = rclpy.create_node('quiet', context=ros_context)      # never spun
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pose = talker.create_publisher(PoseStamped, 'pose', reliable)
    wrench = talker.create_publisher(WrenchStamped, 'wrench', reliable)
    tensions = talker.create_publisher(JointState, 'cable_tensions', reliable)
    pose.publish(PoseStamped())                  # before anyone listens
    for _ in range(2):
        wrench.publish(WrenchStamped())
    recorder = Recorder(quiet, tmp_path / 'late.mcap',
                        ['pose', 'wrench', 'cable_tensions'])
    assert wait_until(lambda: all(p.get_subscription_count() == 1
                                  for p in (pose, wrench, tensions)), 10.0,
                      recorder.poll)
    for _ in range(3):
        wrench.publish(WrenchStamped())
        tensions.publish(JointState())
    assert wait_until(lambda: recorder.topic_counts['/wrench'] == 3
                      and recorder.topic_counts['/cable_tensions'] == 3, 10.0,
                      recorder.poll)
    summary = recorder.close()
    assert summary.topics == {'/pose': 0, '/wrench': 3, '/cable_tensions': 3}
    by_topic = {line.split(':')[0]: line for line in summary.warnings}
    assert sorted(by_topic) == ['/pose', '/wrench'], summary.warnings
    assert 'no message recorded' in by_topic['/pose']
    assert 'the first 2 message(s)' in by_topic['/wrench']
    assert all('\n' not in line for line in summary.warnings)


# ----------------------------------------------------------------------------- salvage


def chunk_census(path: Path) -> list:
    """(offset, length, messages) of each chunk of an intact file, counted by the mcap
    library's stream reader (records inside each chunk) and located by its chunk index."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk, StreamReader
    with open(path, 'rb') as stream:
        counts = [sum(isinstance(r, Message) for r in breakup_chunk(record))
                  for record in StreamReader(stream, emit_chunks=True).records
                  if isinstance(record, Chunk)]
    with open(path, 'rb') as stream:
        indexes = sorted(make_reader(stream).get_summary().chunk_indexes,
                         key=lambda c: c.chunk_start_offset)
    assert len(indexes) == len(counts)
    return [(c.chunk_start_offset, c.chunk_length, n) for c, n in zip(indexes, counts)]


@pytest.fixture(scope='module', params=['none', 'zstd'])
def chunked_log(request, tmp_path_factory):
    """5 s of 1 kHz wrenches and 50 Hz poses in 32 KiB chunks (uncompressed or zstd): the
    file's bytes and its chunk census."""
    from cdpr_dynamics.recording import scenarios
    path = tmp_path_factory.mktemp('salvage') / f'log_{request.param}.mcap'
    scenarios.write_long_log(path, 5.0, compression=request.param, chunk_size=32 * 1024)
    census = chunk_census(path)
    assert len(census) >= 8
    return path.read_bytes(), census


def damage_at(data: bytes, offset: int) -> bytes:
    damaged = bytearray(data)
    damaged[offset] ^= 0xFF
    return bytes(damaged)


@pytest.mark.parametrize('where', ['chunk payload', 'chunk length', 'chunk records length',
                                   'summary', 'footer'])
def test_damage_costs_the_damaged_chunk_only(where, chunked_log, tmp_path, ros_env):
    """One flipped byte: --allow-incomplete reads and --recover keeps every message outside
    the damaged chunk (none lost where the damage is in the summary or footer), counted
    against the mcap library's census of the intact file; the strict read refuses in one
    line; cdpr_record --recover names the damage, no traceback."""
    data, census = chunked_log
    k = 3
    offset, length, _ = census[k]
    compression_length = 4 if b'zstd' in data[offset:offset + 60] else 0
    at = {'chunk payload': offset + length - 100,
          'chunk length': offset + 3,
          'chunk records length': offset + 9 + 28 + 4 + compression_length + 1,
          'summary': len(data) - 8 - 29 - 400,
          'footer': len(data) - 8 - 12}[where]
    lost = 0 if where in ('summary', 'footer') else census[k][2]
    total = sum(n for _, _, n in census)
    path = tmp_path / 'damaged.mcap'
    path.write_bytes(damage_at(data, at))
    with pytest.raises(RecordingError) as caught:
        list(read_messages(path))
    assert '\n' not in str(caught.value) and '--allow-incomplete' in str(caught.value)
    assert sum(1 for _ in read_messages(path, allow_incomplete=True)) == total - lost
    recovered = tmp_path / 'recovered.mcap'
    result = record_cli(ros_env, '--recover', path, recovered)
    assert result.returncode == 0 and 'Traceback' not in result.stderr, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith(f'cdpr_record: recovered {total - lost} messages from '), lines
    if where == 'chunk payload':
        assert f'chunk {k} at byte {offset}' in lines[1], lines
    else:
        assert 'scan' in lines[1], lines
    with open(recovered, 'rb') as stream:
        assert sum(1 for _ in make_reader(stream, validate_crcs=True).iter_messages()) == \
            total - lost


# ----------------------------------------------------------------------------- runs of messages


def test_a_run_of_stamped_messages_decodes_and_encodes_as_each_alone():
    """decode_stamped_run / encode_stamped_run: rclpy's bytes of WrenchStamped messages
    (frame ids of several lengths: other paddings) read back as each message's
    decode_stamped, and written as rclpy writes them; a run stops at the first message of
    another layout (another frame id, length or byte order)."""
    from builtin_interfaces.msg import Time

    from cdpr_dynamics.recording.cdr import serialize
    from msg_adapters.wrench import wrench_message

    rng = np.random.default_rng(3)
    for frame in ('', 'w', 'world', 'a_frame_of_13'):
        stamps = 1_700_000_000_000_000_000 + np.arange(8) * 999_999_937
        values = rng.normal(size=(8, 6)) * 1e3
        datas = [serialize(wrench_message(v[:3], v[3:], frame,
                                          Time(sec=int(t // 10**9), nanosec=int(t % 10**9))))
                 for t, v in zip(stamps, values)]
        assert mcap_schema.encode_stamped_run(stamps, frame, values) == datas
        count, got, got_frame, got_values = mcap_schema.decode_stamped_run(datas, 6)
        assert (count, got_frame) == (8, frame)
        for k, data in enumerate(datas):
            assert (int(got[k]), frame, tuple(got_values[k])) == mcap_schema.decode_stamped(
                data, 6)
        other = serialize(wrench_message(values[0, :3], values[0, 3:], frame + 'x'))
        big_endian = b'\x00\x00' + datas[0][2:]
        for odd in (other, datas[0] + b'\0' * 8, big_endian):
            assert mcap_schema.decode_stamped_run(datas[:5] + [odd] + datas[5:], 6)[0] == 5
        assert mcap_schema.decode_stamped_run([big_endian] + datas, 6)[0] == 0


def test_messages_written_in_bulk_make_the_same_file(tmp_path):
    """RecordingWriter.write_many of runs of messages on several channels writes the file that
    the channel writers write one message at a time, byte for byte (records, message indexes,
    chunk boundaries: small chunks, so that runs cross them)."""
    from cdpr_dynamics.recording.writer import RecordingWriter

    rng = np.random.default_rng(7)
    topics = ('/a', '/b', '/c')
    messages = [(topics[rng.integers(3)], rng.bytes(int(rng.integers(1, 300))),
                 10_000 + 7 * k - int(rng.integers(0, 50)), 5 + k) for k in range(5000)]
    runs = np.cumsum(rng.integers(1, 400, size=100))
    for folder, bulk in (('single', False), ('bulk', True)):
        (tmp_path / folder).mkdir()
        with RecordingWriter(tmp_path / folder / 'out.mcap', chunk_size=16 * 1024) as writer:
            for topic in topics:
                writer.add_topic(topic, 'std_msgs/msg/String')
            ids = {topic: writer.channel_id(topic) for topic in topics}
            for start, end in zip([0, *runs[:-1]], runs):
                run = messages[start:end]
                if bulk and run:
                    writer.write_many([ids[m[0]] for m in run], [m[1] for m in run],
                                      [m[2] for m in run], [m[3] for m in run])
                    continue
                for topic, data, log_time, publish_time in run:
                    writer.channel_writer(topic)(data, log_time, publish_time)
    single = (tmp_path / 'single' / 'out.mcap').read_bytes()
    assert single == (tmp_path / 'bulk' / 'out.mcap').read_bytes()
    with open(tmp_path / 'bulk' / 'out.mcap', 'rb') as stream:
        assert sum(1 for _ in make_reader(stream).iter_messages()) == 5000

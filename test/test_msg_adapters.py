"""msg_adapters at the message level, no DDS: conversions, checks and their reasons."""
import math

import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters

from msg_adapters import diagnostics as diag
from msg_adapters.displacement import displacement_message, read_displacement
from msg_adapters.frf_service import (ARRAYS, FrequencyResponseError, pack_response,
                                      parse_request, request_message, settings_changes,
                                      unpack_response)
from msg_adapters.joint_state import read_tensions, tensions_message
from msg_adapters.pose import pose_message, read_pose
from msg_adapters.validation import InvalidMessage, s_to_stamp, stamp_to_ns, stamp_to_s
from msg_adapters.wrench import read_wrench, wrench_message


def test_stamp_round_trip():
    stamp = s_to_stamp(1712345678.123456789)
    assert stamp.sec == 1712345678
    assert abs(stamp.nanosec - 123456789) <= 256       # float seconds carry ~0.2 us here
    assert stamp_to_ns(s_to_stamp(12.5)) == 12_500_000_000
    assert stamp_to_s(s_to_stamp(3.25)) == 3.25


def test_pose_round_trip_and_normalisation():
    q = np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)]) * (1 + 5e-4)
    msg = pose_message([0.1, -0.2, 1.3], q, 'world', s_to_stamp(2.0))
    pose = read_pose(msg, 'world', 1e-3, last_stamp_ns=1_000_000_000)
    np.testing.assert_array_equal(pose.position_m, [0.1, -0.2, 1.3])
    assert np.linalg.norm(pose.quaternion) == pytest.approx(1.0, abs=1e-15)
    assert pose.stamp_ns == 2_000_000_000


@pytest.mark.parametrize('position, quaternion, frame, last_s, kind, words', [
    ([math.nan, 0, 1], (0, 0, 0, 1), 'world', None, 'not_finite', 'position is not finite'),
    ([0, 0, 1], (0, 0, math.inf, 1), 'world', None, 'not_finite', 'orientation is not finite'),
    ([0, 0, 1], (0, 0, 0, 1.5), 'world', None, 'quaternion', 'not a unit quaternion'),
    ([0, 0, 1], (0, 0, 0, 0), 'world', None, 'quaternion', 'norm 0'),
    ([0, 0, 1], (0, 0, 0, 1), 'map', None, 'frame', "frame 'map', expected 'world'"),
    ([0, 0, 1], (0, 0, 0, 1), '', None, 'frame', 'empty frame_id'),
    ([0, 0, 1], (0, 0, 0, 1), 'world', 5.0, 'stamp', 'out of order'),
])
def test_pose_rejections(position, quaternion, frame, last_s, kind, words):
    msg = pose_message(position, quaternion, frame, s_to_stamp(4.0))
    last = None if last_s is None else int(last_s * 1e9)
    with pytest.raises(InvalidMessage) as err:
        read_pose(msg, 'world', 1e-3, last)
    assert err.value.kind == kind
    assert words in str(err.value)
    assert '\n' not in str(err.value)


def test_pose_equal_stamp_is_in_order():
    msg = pose_message([0, 0, 1], stamp=s_to_stamp(4.0), frame_id='world')
    assert read_pose(msg, 'world', last_stamp_ns=4_000_000_000).stamp_ns == 4_000_000_000


def test_wrench_round_trip_and_rejections():
    msg = wrench_message([1, 2, 3], [4, 5, 6], 'world', s_to_stamp(1.5))
    w = read_wrench(msg, 'world', last_stamp_ns=0)
    np.testing.assert_array_equal(w.force_n, [1, 2, 3])
    np.testing.assert_array_equal(w.moment_nm, [4, 5, 6])
    assert w.stamp_ns == 1_500_000_000
    cases = [(wrench_message([math.nan, 0, 0], frame_id='world'), None, 'not_finite'),
             (wrench_message([0, 0, 0], [0, -math.inf, 0], frame_id='world'), None,
              'not_finite'),
             (wrench_message([0, 0, 0], frame_id='tool0'), None, 'frame'),
             (wrench_message([0, 0, 0], frame_id='world', stamp=s_to_stamp(1.0)),
              2_000_000_000, 'stamp')]
    for bad, last, kind in cases:
        with pytest.raises(InvalidMessage) as err:
            read_wrench(bad, 'world', last)
        assert err.value.kind == kind


def test_displacement_and_tensions():
    msg = displacement_message(np.array([1e-3, -2e-3, 3e-3]), 'world', s_to_stamp(7.0))
    assert msg.header.frame_id == 'world' and msg.header.stamp.sec == 7
    np.testing.assert_array_equal(read_displacement(msg), [1e-3, -2e-3, 3e-3])
    lengths, tensions = np.arange(1.0, 11.0), np.arange(100.0, 110.0)
    js = tensions_message(lengths, tensions, s_to_stamp(1.0), 'world')
    assert js.name[0] == 'cable_0' and js.name[-1] == 'cable_9'
    assert list(js.velocity) == []
    got_l, got_t = read_tensions(js)
    np.testing.assert_array_equal(got_l, lengths)
    np.testing.assert_array_equal(got_t, tensions)


def test_parse_request_splits_names_and_overrides():
    req = parse_request(['amplitude_z_m', 'method=spring', 'n_points=50', 'f_max_hz = 20',
                         'force_x_n=100', 'frequency_hz', 'elements_per_cable=8.0'])
    assert req.names == ['amplitude_z_m', 'frequency_hz']
    assert req.overrides == {'method': 'spring', 'n_points': 50, 'f_max_hz': 20.0,
                             'force_x_n': 100.0, 'elements_per_cable': 8}
    assert req.error == ''
    changes = settings_changes(req.overrides, [0.0, 0.0, 1500.0])
    np.testing.assert_array_equal(changes.pop('frf_force_n'), [100.0, 0.0, 1500.0])
    assert changes == {'method': 'spring', 'n_points': 50, 'f_max_hz': 20.0,
                       'elements_per_cable': 8}
    assert req.key() == parse_request(list(reversed(
        ['method=spring', 'n_points=50', 'f_max_hz=20', 'force_x_n=100',
         'elements_per_cable=8']))).key()


@pytest.mark.parametrize('entry, words', [
    ('colour=red', "unknown override 'colour'"),
    ('n_points=many', 'is not a number'),
    ('n_points=10.5', 'is not an integer'),
    ('f_max_hz=nan', 'is not finite'),
    ('method=', 'empty value'),
])
def test_parse_request_override_errors(entry, words):
    req = parse_request(['frequency_hz', entry])
    assert words in req.error
    values = pack_response(req.names, None, req.error).values
    assert [v.type for v in values] == [ParameterType.PARAMETER_STRING]
    assert words in values[0].string_value


def test_pack_and_unpack_response():
    arrays = {name: np.linspace(0, 1, 5) + i for i, name in enumerate(ARRAYS)}
    arrays['log10_amplitude_z'][0] = -np.inf
    request = request_message(['frequency_hz', 'nope', 'log10_amplitude_z'],
                              {'n_points': 5, 'f_max_hz': 0.1 + 0.2})
    assert request.names[-1] == 'f_max_hz=0.30000000000000004'   # exact round trip
    parsed = parse_request(request.names)
    assert parsed.overrides['f_max_hz'] == 0.1 + 0.2
    response = pack_response(parsed.names, arrays)
    assert [v.type for v in response.values] == [ParameterType.PARAMETER_DOUBLE_ARRAY,
                                                 ParameterType.PARAMETER_STRING,
                                                 ParameterType.PARAMETER_DOUBLE_ARRAY]
    got, reasons = unpack_response(request, response)
    np.testing.assert_array_equal(got['frequency_hz'], arrays['frequency_hz'])
    np.testing.assert_array_equal(got['log10_amplitude_z'], arrays['log10_amplitude_z'])
    assert "unknown array 'nope'" in reasons['nope']
    failed = pack_response(parsed.names, None, 'frequency response failed: because')
    _, reasons = unpack_response(request, failed)
    assert reasons['frequency_hz'] == 'frequency response failed: because'
    with pytest.raises(FrequencyResponseError):
        unpack_response(request, GetParameters.Response())


def test_default_request_asks_for_every_array():
    assert list(request_message().names) == list(ARRAYS)
    assert pack_response([], None).values == []


def test_diagnostics_round_trip():
    status = diag.status_message('n: model', diag.WARN, 'heavy damping',
                                 {'dofs': 363, 'update_ms': 1.23456789, 'pose': [0.0, 1.5]},
                                 'hw')
    statuses = diag.read_statuses(diag.diagnostics_message([status]))
    assert statuses['n: model'] == {'level': diag.WARN, 'message': 'heavy damping',
                                    'values': {'dofs': '363', 'update_ms': '1.23457',
                                               'pose': '0; 1.5'}}

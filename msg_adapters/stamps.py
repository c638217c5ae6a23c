"""The node's policy for input stamps: stamps never latch the node (doc/node_interface.md).

One :class:`StampClock` per input stream (pose, wrench) decides what each stamp means, given the
node's clock ``now`` (ns; ``None`` where there is none):

* **Unstamped** (stamp 0, common from simple controllers): ``zero_stamp = 'reject'`` rejects it
  with the reason; ``'arrival'`` times it by its arrival (the node's clock). Never a silent
  prediction at t = 0 (every wrench at one instant predicts exactly 0).
* **Ahead of the node's clock** by more than ``max_ahead_s``: rejected, and not taken as the
  reference (one wrench stamped in 2038 no longer makes every later one "old").
* **Older than the last accepted** by at most ``jump_back_s``: out of order, rejected (reordered
  best-effort traffic). By more: the sender's clock jumped back (a restarted controller, a
  replayed log): accepted with a warning, the stream restarts at the new stamp (the wrench
  integrator keeps its state of motion and takes the new stamp as its time origin).

ROS-free apart from :class:`~msg_adapters.validation.InvalidMessage`.
"""
from __future__ import annotations

from dataclasses import dataclass

from msg_adapters.validation import InvalidMessage

ZERO_STAMP_POLICIES = ('reject', 'arrival')


@dataclass(frozen=True)
class StampPolicy:
    """``node.max_stamp_ahead_s``, ``node.clock_jump_back_s`` and ``node.zero_stamp``."""

    max_ahead_s: float = 1.0
    jump_back_s: float = 1.0
    zero_stamp: str = 'reject'

    @classmethod
    def from_options(cls, options: dict) -> 'StampPolicy':
        """From validated ``node.*`` values
        (:func:`cdpr_dynamics.analysis.config.node_options`)."""
        return cls(options['node.max_stamp_ahead_s'], options['node.clock_jump_back_s'],
                   options['node.zero_stamp'])


@dataclass(frozen=True)
class Stamp:
    """The time an input is taken at (ns); ``jumped``: the clock jumped back (``note`` why)."""

    ns: int
    jumped: bool = False
    note: str = ''


class StampClock:
    """The stamps of one input stream (``what``: 'pose' or 'wrench'); see the module docstring.

    :meth:`check` returns the :class:`Stamp` or raises :class:`InvalidMessage` (kind 'stamp'
    or 'future'); :meth:`accept` then records the stamp once the input was used.
    """

    def __init__(self, what: str, policy: StampPolicy = StampPolicy()):
        self.what = what
        self.policy = policy
        self.last_ns: int | None = None

    def check(self, stamp_ns: int, now_ns: int | None = None) -> Stamp:
        what, policy = self.what, self.policy
        if stamp_ns == 0:
            if policy.zero_stamp != 'arrival':
                raise InvalidMessage(f'{what} is unstamped (stamp 0): rejected; stamp it, or set '
                                     f'node.zero_stamp to arrival to time unstamped inputs by '
                                     f'their arrival', 'stamp')
            if not now_ns:
                raise InvalidMessage(f'{what} is unstamped and the node has no clock to time it '
                                     f'by (it reads 0: use_sim_time without /clock?)', 'stamp')
            stamp_ns = int(now_ns)
        elif now_ns and stamp_ns - now_ns > policy.max_ahead_s * 1e9:
            raise InvalidMessage(f'{what} stamp {stamp_ns * 1e-9:.6f} s is '
                                 f'{(stamp_ns - now_ns) * 1e-9:.6g} s ahead of the node clock '
                                 f'({now_ns * 1e-9:.6f} s), over node.max_stamp_ahead_s = '
                                 f'{policy.max_ahead_s:g}: rejected, not taken as the time '
                                 f'reference', 'future')
        last = self.last_ns
        if last is None or stamp_ns >= last:
            return Stamp(stamp_ns)
        back = (last - stamp_ns) * 1e-9
        if back <= policy.jump_back_s:
            raise InvalidMessage(f'{what} stamp {stamp_ns * 1e-9:.6f} s is older than the last '
                                 f'accepted one ({last * 1e-9:.6f} s): out of order', 'stamp')
        return Stamp(stamp_ns, True, f'{what} clock jumped back {back:.6g} s (from '
                                     f'{last * 1e-9:.6f} s to {stamp_ns * 1e-9:.6f} s, over '
                                     f'node.clock_jump_back_s = {policy.jump_back_s:g}): '
                                     f'restarted at the new stamp')

    def accept(self, stamp: Stamp) -> None:
        self.last_ns = stamp.ns


def handle_in_stamp_order(held, takes, handles, budget: int) -> None:
    """Hand input messages to their handlers in header-stamp order across the inputs.

    ``held[i]`` is the message already taken from input ``i`` (None: none), ``takes[i]()`` the
    next one waiting there (None: none), ``handles[i]`` its handler. Each turn takes one message
    from every input whose slot is empty and hands on the earliest held one: at equal stamps the
    lower index first, an unstamped message (stamp 0, timed by its arrival) before any stamped
    one. So a pose applies to exactly the wrenches stamped at or after it, also when the node
    runs behind and both inputs have a backlog (each input's queue is in its own stamp order).
    After ``budget`` turns nothing more is taken: what is still held is handed on, the rest
    waits for the next call.
    """
    held = list(held)

    def order(i):
        stamp = held[i].header.stamp
        return (stamp.sec * 1_000_000_000 + stamp.nanosec) or -1, i

    for turn in range(budget + len(held)):
        if turn < budget:
            held = [msg if msg is not None else take() for msg, take in zip(held, takes)]
        waiting = [i for i, msg in enumerate(held) if msg is not None]
        if not waiting:
            return
        first = min(waiting, key=order)
        msg, held[first] = held[first], None
        handles[first](msg)

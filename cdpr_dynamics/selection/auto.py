"""Method ``auto``: the cheapest cable model whose estimated error over the band is within
``model.tolerance``, among the models within the compute budget ``model.max_dofs``.

The estimates are :mod:`cdpr_dynamics.selection.estimates` (closed forms, no eigen-solution); the
yardstick they are checked against is :mod:`cdpr_dynamics.selection.reference`.

**Choice.** Candidates in order of cost (compute time grows with the DOFs; at equal DOFs
straight before sagged): spring, fem n = 1, catenary, catenary_exact (3 or 6 DOFs), then fem
and fem_sag with the smallest n that passes, ``SAFETY * estimate <= tolerance``. A candidate
with more DOFs (platform + 3 per interior cable node) than ``model.max_dofs`` is never taken
(n is also at most :data:`MAX_ELEMENTS`). ``dsm`` is not a candidate: it has no finite
matrices, so no time history for the node.

**Nothing within the budget passes.** Then ``auto`` takes the most accurate model within the
budget (smallest estimated error, then fewest missed cable modes, then cost), never a massless
model merely for being cheap, and its reason (``ModelChoice.reason``, and
``ModelChoice.warnings`` for the JSON's ``warnings`` and the node's diagnostics) says so with
the estimated error, and which fem_sag would meet the tolerance with how many DOFs (n from
the n^-2 fall of its error, checked by an estimate: "about", not the smallest such n).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cdpr_dynamics.selection.closed_forms import SelectionError, largest_phase
from cdpr_dynamics.dynamics.system import Damping
from cdpr_dynamics.selection.estimates import MISSED, ErrorEstimate, Estimator, percent

MAX_ELEMENTS = 256          # largest n auto considers (fem_sag n = 256: 6123 DOFs, 8 cables)
SAFETY = 1.25               # auto needs SAFETY * estimate <= tolerance (test_cli_estimate_table)
MASSLESS = ('spring', 'fem', 'catenary', 'catenary_exact')   # in this order at n = 1
STEP = 1.25                 # n grows by this factor while the estimate is above the tolerance


@dataclass(frozen=True)
class ModelChoice:
    """What ``auto`` chose, why (one line), and its estimated relative error over the band
    (not capped: 3.8 is 380 %); ``meets_tolerance`` False when nothing within the budget did."""

    method: str
    elements_per_cable: int
    reason: str
    estimated_error: float
    estimated_freq_error: float = 0.0
    estimated_frf_error: float = 0.0
    considered: tuple = field(default=(), compare=False)   # (method, n, estimate) in cost order
    dofs: int = 0
    meets_tolerance: bool = True

    @property
    def warnings(self) -> tuple[str, ...]:
        """The warning analyses and the node show when the choice misses the tolerance."""
        return () if self.meets_tolerance else (f'accuracy: {self.reason}',)


def model_dofs(n: int, n_cables: int, platform_dofs: int) -> int:
    """DOFs of a model with n elements per cable: platform + 3 per interior node."""
    return platform_dofs + 3 * n_cables * (n - 1)


def _cost(method: str, n: int, n_cables: int, platform_dofs: int) -> float:
    """Relative compute cost: the DOFs (time grows with them: build + FRF + modes took 1.4 ms
    at 3 DOFs, 19 ms at 363, 38 ms at 1515 for fem; fem_sag 1.3 times fem at equal DOFs),
    ties broken by kind."""
    dofs = model_dofs(n, n_cables, platform_dofs)
    rank = {'spring': 0.0, 'fem': 0.1, 'catenary': 0.2, 'catenary_exact': 0.3}
    if method == 'fem_sag':
        return 1.3 * dofs + 0.4
    return dofs + rank.get(method, 0.0)


def _smallest_passing(est: Estimator, family: str, start: int, largest: int, passes):
    """(estimates tried, the smallest passing n's estimate or None) for n in [start, largest]:
    errors fall as n^-2 once the modes are resolved, so aim there (at least STEP n), then
    bisect down."""
    tried = []
    n, failed = start, start - 1
    while True:
        e = est.estimate(family, n)
        tried.append(e)
        if passes(e) or n >= largest:
            break
        aim = n * math.sqrt(SAFETY * e.error / est.settings.tolerance) \
            if not e.missed_modes else STEP * n
        failed, n = n, min(largest, max(n + 1, math.ceil(max(aim, STEP * n))))
    if not passes(e):
        return tried, None
    while n - failed > 1:
        mid = (n + failed) // 2
        trial = est.estimate(family, mid)
        tried.append(trial)
        if passes(trial):
            n, e = mid, trial
        else:
            failed = mid
    return tried, e


def choose_model(settings, eq, f_max_hz: float | None = None,
                 damping: Damping | None = None) -> ModelChoice:
    """The cheapest model within ``model.max_dofs`` estimated within ``model.tolerance`` over
    [0, f_max], or the most accurate one within the budget (module doc).

    ``f_max_hz`` defaults to ``frf.f_max_hz``; ``damping`` to the configured one
    (:func:`cdpr_dynamics.selection.estimates.band_damping`: a ``damping.modal_ratio`` is fitted
    on the
    spring model's modes). Raises :class:`SelectionError` (a ValueError) when no model
    describes the scene (a cable without tension) or the budget is below the platform's DOFs.
    """
    est = Estimator(settings, eq, f_max_hz, damping)
    tol = float(settings.tolerance)
    nd = est.truth_system.platform_dofs
    ncab = eq.cables.n_cables
    budget = int(settings.max_dofs)
    if budget < nd:
        raise SelectionError(f'model.max_dofs = {budget} is below the platform\'s {nd} DOFs: '
                             'no model fits the budget')
    largest = max(1, min(MAX_ELEMENTS, (budget - nd) // (3 * ncab) + 1))

    def cost(e: ErrorEstimate) -> float:
        return _cost(e.method, e.elements_per_cable, ncab, nd)

    def passes(e: ErrorEstimate) -> bool:
        return SAFETY * e.error <= tol

    candidates = [est.estimate(m, 1, full=False) for m in MASSLESS]
    notes = []                         # rejected families, for the reason only
    sc = est.scene
    top = int(max(sc.transverse_in_band.max(), sc.axial_in_band.max()))
    start = max(2, top + 1, math.ceil(top * math.pi / largest_phase(tol / SAFETY)))
    straight_fails = False
    for family in ('fem', 'fem_sag') if largest >= 2 else ():
        if family == 'fem':
            limit = est.estimate('dsm', 0)      # fem as n -> inf: sag errors do not shrink
            if not passes(limit):
                straight_fails = True
                notes.append(ErrorEstimate('fem', MAX_ELEMENTS + 1, limit.freq_error,
                                           limit.frf_error, f'straight cables: {limit.cause}'))
                continue
        tried, _ = _smallest_passing(est, family, min(start, largest), largest, passes)
        candidates += tried
    band = f'0-{sc.f_max_hz:g} Hz'
    found = [c for c in candidates if passes(c)]
    if found:
        best = min(found, key=cost)
        rejected = _rejections([c for c in candidates + notes if not passes(c)
                                and (cost(c) < cost(best) or c.method != best.method)])
        reason = (f'auto: {_label(best)}, the cheapest model estimated within model.tolerance '
                  f'{100 * tol:g} % over {band} ({percent(best.error)} %: {best.cause})'
                  + (f'; rejected: {rejected}' if rejected else ''))
    else:
        # look at every candidate in full, the straight chain too where its limit failed
        candidates = [est.estimate(c.method, c.elements_per_cable) if math.isnan(c.frf_error)
                      else c for c in candidates]
        if straight_fails and largest >= 2:
            candidates.append(est.estimate('fem', largest))
        best = min(candidates, key=lambda c: (c.error, c.missed_modes, cost(c)))
        limit_text = (f'model.max_dofs {budget}' if largest < MAX_ELEMENTS
                      else f'n <= {MAX_ELEMENTS}')
        reason = (f'auto: no model within {limit_text} meets model.tolerance {100 * tol:g} % '
                  f'over {band}; {_label(best)} '
                  f'({model_dofs(best.elements_per_cable, ncab, nd)} DOFs) is the most '
                  f'accurate within it, estimated {percent(best.error)} % off ({best.cause})')
        if largest < MAX_ELEMENTS:
            inside = [c for c in candidates if c.method == 'fem_sag']
            reason += _beyond_budget(est, max(inside, key=lambda c: c.elements_per_cable,
                                              default=None), passes, ncab, nd)
    considered = tuple((c.method, c.elements_per_cable, c.error) for c in candidates + notes)
    return ModelChoice(best.method, best.elements_per_cable, reason, best.error,
                       best.freq_error, best.frf_error, considered,
                       model_dofs(best.elements_per_cable, ncab, nd), bool(found))


def _beyond_budget(est: Estimator, inside: ErrorEstimate | None, passes, n_cables: int,
                   nd: int) -> str:
    """'; fem_sag n=44 (1035 DOFs) would meet it ...': fem_sag past the budget, from the n^-2
    fall of its error from ``inside`` (fem_sag at the budget's largest n), checked by an
    estimate (at most three: n grows by STEP while it does not pass)."""
    if inside is None or inside.missed_modes:
        return ''
    tol = est.settings.tolerance
    n = inside.elements_per_cable
    aim = math.ceil(n * math.sqrt(SAFETY * inside.error / tol))
    for _ in range(3):
        n = min(MAX_ELEMENTS, max(n + 1, aim))
        e = est.estimate('fem_sag', n)
        if passes(e):
            dofs = model_dofs(n, n_cables, nd)
            return f'; {_label(e)} ({dofs} DOFs) would meet it with model.max_dofs >= {dofs}'
        if n >= MAX_ELEMENTS:
            break
        aim = math.ceil(STEP * n)
    return f'; fem_sag would need more than n = {n} to meet it'


def _label(e: ErrorEstimate) -> str:
    return f'{e.method} n={e.elements_per_cable}' if e.method in ('fem', 'fem_sag') \
        else e.method


def _rejections(rejected: list[ErrorEstimate]) -> str:
    """'spring (misses ...), fem n<=12 (...)': the finest rejected candidate of each method."""
    last: dict[str, ErrorEstimate] = {}
    for c in rejected:
        key = c.method if c.method not in ('fem', 'fem_sag') or c.elements_per_cable > 1 \
            else f'{c.method}1'
        if key not in last or c.elements_per_cable > last[key].elements_per_cable:
            last[key] = c
    groups: dict[str, list[str]] = {}
    for c in last.values():
        if c.method in ('fem', 'fem_sag') and c.elements_per_cable > MAX_ELEMENTS:
            name = f'{c.method} (any n)'
        elif c.method in ('fem', 'fem_sag') and c.elements_per_cable > 1:
            name = f'{c.method} n<={c.elements_per_cable}'
        else:
            name = _label(c)
        cause = c.cause if c.missed_modes or c.error >= MISSED \
            else f'{percent(c.error)} %: {c.cause}'
        groups.setdefault(cause, []).append(name)
    return '; '.join(f'{", ".join(names)} ({cause})' for cause, names in groups.items())


def accuracy_warnings(settings, eq, method: str, n: int,
                      f_max_hz: float | None = None) -> list[str]:
    """Warnings when a configured model is estimated off by more than ``model.tolerance``.

    E.g. fem with too few elements for the cable modes in the band, a massless model that
    misses them, a straight model that ignores sag. Empty for a scene without estimates
    (slack cables: the models' own warnings say why).
    """
    if method == 'auto':
        return []
    try:
        est = Estimator(settings, eq, f_max_hz)
        e = est.estimate(method, n)
    except (SelectionError, np.linalg.LinAlgError):
        return []
    tol = float(settings.tolerance)
    if not e.error > tol:
        return []
    size = f' n={e.elements_per_cable}' if method in ('fem', 'fem_sag') else ''
    return [f'accuracy: {method}{size} is estimated {percent(e.error)} % off over '
            f'0-{est.scene.f_max_hz:g} Hz (> model.tolerance {100 * tol:g} %): {e.cause}; '
            'model.method auto picks a model that meets it']

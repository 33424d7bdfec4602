r"""Persistent dense QP solvers for the MPC: ProxSuite (default) and DAQP.

Both solve

.. math::

    \min_z \tfrac12 z^T H z + g^T z \quad \text{s.t.} \quad
    l \le C z \le u, \quad lb \le z \le ub

keeping one workspace alive between calls: the first call sets the problem up, later
calls only update the data (docs/paper.md §7, measured facts of ProxSuite on this QP).

ProxSuite's tolerances and iteration limits (``eps_abs``, ``eps_rel``, the infeasibility
tolerances, ``max_iter``, ``max_inner_iter``) are fields of
:class:`~wip_control.core.mpc.MpcParams`; its initial guess (cold start with the previous
result) and dense backend (``PrimalDualLDLT``) are set here. Why each, with the measured
failures of the alternatives: docs/decisions/proxsuite-settings.md.

After a failed solve the workspace is set up afresh, so that a bad iterate never seeds the
next solve; a failed solve is retried once from the equality-constrained initial guess,
and if that stalls too, DAQP solves the same data before the caller falls back to its
previous plan.

Every point ProxSuite reports as solved is *polished*: the equality-constrained problem on
the active set it found (multipliers larger than ``eps_abs``) is solved (compiled, a fixed
order of IEEE operations: :mod:`.qp_polish`), and the result replaces ProxSuite's when it
is primal feasible and its multipliers have the right signs (else DAQP solves the same
data). The polished point depends only on the data and the active set, so the same
scenario gives the same bits in every process (docs/decisions/determinism.md).
"""

from __future__ import annotations

import atexit
import enum
from typing import NamedTuple
import weakref

import daqp
import numpy as np
import proxsuite

from .compiled import load_compiled, QP_POLISH

_PROXQP = proxsuite.proxqp
_PROXQP_DENSE = _PROXQP.dense


class MpcStatus(enum.IntEnum):
    """Outcome of one MPC tick; ``int(status)`` is recorded, ``status.name`` is the text."""

    SOLVED = 0
    MAX_ITER_REACHED = 1
    PRIMAL_INFEASIBLE = 2
    DUAL_INFEASIBLE = 3
    SOLVED_CLOSEST_PRIMAL_FEASIBLE = 4
    NOT_RUN = 5
    #: The solver returned something that is not a finite vector.
    NON_FINITE_SOLUTION = 6
    #: Any other solver error code (DAQP cycling, singular or non-convex problem, ...).
    SOLVER_ERROR = 7
    #: The MPC did not call the solver: an estimate, the reference or the limit was NaN/inf.
    INPUT_INVALID = 8


_PROXSUITE_STATUS = {
    _PROXQP.PROXQP_SOLVED: MpcStatus.SOLVED,
    _PROXQP.PROXQP_MAX_ITER_REACHED: MpcStatus.MAX_ITER_REACHED,
    _PROXQP.PROXQP_PRIMAL_INFEASIBLE: MpcStatus.PRIMAL_INFEASIBLE,
    _PROXQP.PROXQP_DUAL_INFEASIBLE: MpcStatus.DUAL_INFEASIBLE,
    _PROXQP.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: MpcStatus.SOLVED_CLOSEST_PRIMAL_FEASIBLE,
    _PROXQP.PROXQP_NOT_RUN: MpcStatus.NOT_RUN,
}

# DAQP exit flags (https://darnstrom.github.io/daqp/parameters): 1 optimal, 2 soft
# optimal, -1 infeasible, -3 unbounded, -4 iteration limit; others are numerical errors.
_DAQP_STATUS = {1: MpcStatus.SOLVED, 2: MpcStatus.SOLVED, -1: MpcStatus.PRIMAL_INFEASIBLE,
                -3: MpcStatus.DUAL_INFEASIBLE, -4: MpcStatus.MAX_ITER_REACHED}


class QpSolution(NamedTuple):
    """One solve: primal solution (a copy), status and iteration count."""

    z: np.ndarray
    status: MpcStatus
    iterations: int


class QpSolverParams(NamedTuple):
    """Solver tolerances (ProxSuite names; DAQP uses ``max_iter`` only, it is exact).

    ``polish``: replace ProxSuite's solved point by the exact solution on its active set
    (:func:`polish`); off only to compare with the raw answer.
    """

    eps_abs: float = 1e-6
    eps_rel: float = 1e-11
    eps_primal_inf: float = 0.0
    eps_dual_inf: float = 0.0
    max_iter: int = 1000
    max_inner_iter: int = 30
    polish: bool = True


class PolishStats:
    """Counts of the polish step of one :class:`ProxsuiteSolver` since it was made.

    ``rejected``: solves whose polish failed (``rejected_reasons`` says why, with
    :func:`polish`'s reasons); of those, ``exact`` were replaced by DAQP's solution of
    the same data and the others kept ProxSuite's raw point (not reproducible to the
    last bit across processes).
    """

    def __init__(self) -> None:
        self.polished = 0
        self.rejected = 0
        self.exact = 0
        self.rejected_reasons: dict[str, int] = {}

    @property
    def raw(self) -> int:
        """Solved ticks that kept ProxSuite's raw point."""
        return self.rejected - self.exact

    def __repr__(self) -> str:
        return (f'PolishStats(polished={self.polished}, rejected={self.rejected}, '
                f'exact={self.exact}, rejected_reasons={self.rejected_reasons})')


class PolishResult(NamedTuple):
    """Outcome of :func:`polish`: the point and multipliers, or ``None`` and the reason."""

    z: np.ndarray | None
    multipliers: np.ndarray | None  # ProxSuite's layout: rows of C, then the boxes
    reason: str                     # 'ok' or why the point was rejected


#: Corrections of the active set :func:`polish` makes before it gives up.
POLISH_ROUNDS = 4


def polish(h: np.ndarray, g: np.ndarray, c: np.ndarray, lower: np.ndarray,
           upper: np.ndarray, lower_box: np.ndarray, upper_box: np.ndarray,
           multipliers: np.ndarray, tolerance: float) -> PolishResult:
    """Exact minimiser on the active set given by ``multipliers``, if it is the optimum.

    ``multipliers`` is ProxSuite's ``results.z``: one per row of C, then one per variable
    (box); positive at an upper bound, negative at a lower one, so that
    H z + g + Cᵀ y_C + y_box = 0. A constraint is taken as active when its multiplier
    exceeds ``tolerance`` in magnitude (a smaller one changes stationarity by less than
    the solver's own tolerance; a constraint at its bound with a zero multiplier need not
    be imposed, the optimum of the strictly convex QP satisfies it anyway). With A the
    active rows of [C; I] and b their bounds, the point z and multipliers λ solve the
    KKT system of the equality-constrained QP

        [H  Aᵀ] [z]   [−g]
        [A  0 ] [λ] = [ b]

    by Gaussian elimination with partial pivoting (the fixed variables eliminated;
    compiled, :mod:`.qp_polish`). The point is accepted if every constraint holds within
    ``tolerance``, the stationarity residual is below it, and each λ has the sign of its
    bound (within ``tolerance``): it then satisfies the QP's KKT conditions, so it is its
    unique optimum. Otherwise the violated constraints join the active set and those with
    a wrong-signed λ leave it, up to :data:`POLISH_ROUNDS` times (ProxSuite's multipliers
    of nearly active constraints are only accurate to about its tolerance). An accepted
    set is then reduced to its constraints with |λ| > ``tolerance``, so the result
    depends on the data and the optimum only, not on the solver's round-off.

    The arrays are float64 and C-contiguous (another layout or type compiles anew).
    """
    compiled = _compiled_polish()
    n, m = h.shape[0], c.shape[0]
    z, y = np.empty(n), np.empty(m + n)
    outcome = compiled.polish(h, g, c, lower, upper, lower_box, upper_box, multipliers,
                              float(tolerance), POLISH_ROUNDS, z, y)
    if outcome == compiled.OK:
        return PolishResult(z, y, 'ok')
    return PolishResult(None, None, compiled.REASONS[outcome])


def _compiled_polish():
    """:mod:`.qp_polish`, imported and warmed up by the first call in a process."""
    return load_compiled(QP_POLISH)


def _finite_or_error(z: np.ndarray, status: MpcStatus) -> MpcStatus:
    if status == MpcStatus.SOLVED and not np.isfinite(z).all():
        return MpcStatus.NON_FINITE_SOLUTION
    return status


class ProxsuiteSolver:
    """One persistent ``proxsuite.proxqp.dense.QP`` with box constraints.

    Parameters
    ----------
    n_variables, n_constraints : sizes of z and of the general rows C.
    settings : tolerances and iteration limit.
    """

    name = 'proxsuite'

    def __init__(self, n_variables: int, n_constraints: int, settings: QpSolverParams) -> None:
        self._sizes = (n_variables, n_constraints)
        self._settings = settings
        self._qp = None
        self._exact = None  # DaqpSolver, made on the first double failure
        self.stats = PolishStats()
        if settings.polish:
            _compiled_polish()   # at construction, not in the first control tick
        _LIVE_SOLVERS.add(self)

    def _new_workspace(self, initial_guess=None):
        # A fresh object, not init() on the old one: init() keeps the previous result,
        # which COLD_START_WITH_PREVIOUS_RESULT then uses as its starting point, and from
        # the result of an unrelated QP (after a reset or a failure) ProxSuite returned
        # "solved" points up to 9 N m away from the optimum (residuals small,
        # complementarity not). cleanup() did not make the outcome independent of the
        # history either.
        n_variables, n_constraints = self._sizes
        qp = _PROXQP_DENSE.QP(n_variables, 0, n_constraints, True,
                              _PROXQP_DENSE.HessianType.Dense,
                              _PROXQP_DENSE.DenseBackend.PrimalDualLDLT)
        s = qp.settings
        s.initial_guess = (_PROXQP.InitialGuess.COLD_START_WITH_PREVIOUS_RESULT
                           if initial_guess is None else initial_guess)
        s.eps_abs = self._settings.eps_abs
        s.eps_rel = self._settings.eps_rel
        s.eps_primal_inf = self._settings.eps_primal_inf
        s.eps_dual_inf = self._settings.eps_dual_inf
        s.max_iter = self._settings.max_iter
        s.max_iter_in = self._settings.max_inner_iter
        s.verbose = False
        return qp

    def reset(self) -> None:
        """Forget the previous result: the next call starts from a fresh workspace."""
        self._qp = None

    def solve(self, h: np.ndarray, g: np.ndarray, c: np.ndarray, lower: np.ndarray,
              upper: np.ndarray, lower_box: np.ndarray, upper_box: np.ndarray) -> QpSolution:
        qp = self._qp
        if qp is None:
            qp = self._qp = self._new_workspace()
            qp.init(h, g, None, None, c, lower, upper, lower_box, upper_box)
        else:
            qp.update(H=h, g=g, C=c, l=lower, u=upper, l_box=lower_box, u_box=upper_box)
        qp.solve()
        z, status, iterations = self._result(qp)
        if status != MpcStatus.SOLVED:
            # A few QPs (about 1 in 20 000 random states in the test's ranges; e.g. a
            # large negative τ(k−1) while υd asks for speed) make ProxSuite run to
            # max_iter from its default start, and solve from the equality-constrained
            # initial guess (the other failure-free mode measured, ~2x slower): one retry
            # with it, in a fresh workspace, before the caller falls back to its plan.
            self._qp = None
            retry = self._new_workspace(_PROXQP.InitialGuess.EQUALITY_CONSTRAINED_INITIAL_GUESS)
            retry.init(h, g, None, None, c, lower, upper, lower_box, upper_box)
            retry.solve()
            z_retry, status_retry, iterations_retry = self._result(retry)
            iterations += iterations_retry
            if status_retry == MpcStatus.SOLVED:
                z, status = z_retry, status_retry
            else:
                # Last resort, DAQP (exact dual active set) on the same data: with one
                # slack per step a few badly scaled QPs (τ(k−1) far beyond a shrunken
                # limit, so the held tail diverges and slacks reach ~1e3) stalled ProxSuite
                # from both starts; DAQP solves them.
                if self._exact is None:
                    self._exact = DaqpSolver(*self._sizes, self._settings)
                exact = self._exact.solve(h, g, c, lower, upper, lower_box, upper_box)
                iterations += exact.iterations
                if exact.status == MpcStatus.SOLVED:
                    return QpSolution(exact.z, exact.status, iterations)
                return QpSolution(z, status, iterations)
            qp = retry
        if status == MpcStatus.SOLVED and self._settings.polish:
            z = self._polish(qp, z, h, g, c, lower, upper, lower_box, upper_box)
        return QpSolution(z, status, iterations)

    def _polish(self, qp, z, h, g, c, lower, upper, lower_box, upper_box) -> np.ndarray:
        """ProxSuite's point polished on its active set, or as it is (and counted)."""
        result = polish(h, g, c, lower, upper, lower_box, upper_box,
                        np.array(qp.results.z), self._settings.eps_abs)
        if result.z is None:
            stats = self.stats
            stats.rejected += 1
            stats.rejected_reasons[result.reason] = (
                stats.rejected_reasons.get(result.reason, 0) + 1)
            # The next solve starts from a fresh workspace, not from this raw point.
            self._qp = None
            # DAQP from a fresh workspace: exact and reproducible, and independent of
            # which earlier ticks were rejected. If it fails too, ProxSuite's raw point
            # is kept (solved within its tolerance, but not reproducible to the bit).
            if self._exact is None:
                self._exact = DaqpSolver(*self._sizes, self._settings)
            self._exact.reset()
            exact = self._exact.solve(h, g, c, lower, upper, lower_box, upper_box)
            if exact.status == MpcStatus.SOLVED:
                stats.exact = stats.exact + 1
                return exact.z
            return z
        self.stats.polished += 1
        # The next solve starts from this result (COLD_START_WITH_PREVIOUS_RESULT): from
        # the polished point and multipliers its start is the same in every process, so
        # are its iteration counts.
        qp.results.x = result.z
        qp.results.z = result.multipliers
        return result.z

    @staticmethod
    def _result(qp) -> tuple[np.ndarray, MpcStatus, int]:
        info = qp.results.info
        status = _PROXSUITE_STATUS.get(info.status, MpcStatus.SOLVER_ERROR)
        z = np.array(qp.results.x)
        return z, _finite_or_error(z, status), int(info.iter)


#: The ProxSuite solvers alive, whose workspaces :func:`_release_workspaces` frees at exit.
_LIVE_SOLVERS: 'weakref.WeakSet[ProxsuiteSolver]' = weakref.WeakSet()


@atexit.register
def _release_workspaces() -> None:
    """Free every live ProxSuite workspace before the interpreter tears its modules down.

    Why: a node process still holds its MPC (the executor's nodes) when Python exits, and
    nanobind, ProxSuite's binding layer, reports every object of its types alive at its
    module's teardown as a leak: about 30 lines of 'leaked instance … proxqp.dense.QP …
    likely a reference counting issue' ended every controller log. atexit handlers run
    before that teardown.
    """
    for solver in list(_LIVE_SOLVERS):
        solver.reset()


class DaqpSolver:
    """One persistent ``daqp.Model`` (dual active set; exact up to round-off).

    DAQP takes the variable bounds as the first ``n`` entries of its bound vectors;
    they are packed into buffers owned by this object.
    """

    name = 'daqp'

    def __init__(self, n_variables: int, n_constraints: int, settings: QpSolverParams) -> None:
        self._n = n_variables
        self._upper = np.empty(n_variables + n_constraints)
        self._lower = np.empty(n_variables + n_constraints)
        self._max_iter = int(settings.max_iter)
        self._model: daqp.Model | None = None

    def reset(self) -> None:
        """Drop the workspace (and its active set): the next call sets it up again."""
        self._model = None

    def solve(self, h: np.ndarray, g: np.ndarray, c: np.ndarray, lower: np.ndarray,
              upper: np.ndarray, lower_box: np.ndarray, upper_box: np.ndarray) -> QpSolution:
        n = self._n
        self._upper[:n] = upper_box
        self._upper[n:] = upper
        self._lower[:n] = lower_box
        self._lower[n:] = lower
        if self._model is None:
            model = daqp.Model()
            flag = model.setup(h, g, c, self._upper, self._lower)[0]
            if flag < 0:
                return QpSolution(np.full(n, np.nan), MpcStatus.SOLVER_ERROR, 0)
            model.settings = {'iter_limit': self._max_iter}
            self._model = model
        else:
            self._model.update(H=h, f=g, A=c, bupper=self._upper, blower=self._lower)
        z, _, flag, info = self._model.solve()
        status = _DAQP_STATUS.get(int(flag), MpcStatus.SOLVER_ERROR)
        z = np.array(z, dtype=float)
        status = _finite_or_error(z, status)
        if status != MpcStatus.SOLVED:
            self._model = None
        return QpSolution(z, status, int(info['iterations']))


def make_solver(backend: str, n_variables: int, n_constraints: int,
                settings: QpSolverParams) -> ProxsuiteSolver | DaqpSolver:
    """Return the persistent solver named ``backend`` (``'proxsuite'`` or ``'daqp'``)."""
    if backend == 'proxsuite':
        return ProxsuiteSolver(n_variables, n_constraints, settings)
    if backend == 'daqp':
        return DaqpSolver(n_variables, n_constraints, settings)
    raise ValueError(f"QP backend {backend!r} is not one of ['proxsuite', 'daqp']")

"""What a calibrated sample is worth: its status, its predicted error, and the self-watch.

Statuses (one per sample, `Status`; the numbers are the wire values of ``recal.Status``):

* ``uncalibrated`` (1): no estimate at all and nothing collected toward one (no prior, no
  quasi-static window yet); and, set by the shell, a sample whose calibrated value was not
  finite (published zeroed, `NOT_FINITE_SIGMA_MG`).
* ``bootstrapping`` (2): no estimate yet; quasi-static windows are being collected for the
  first fit. The output is the raw reading over a provisional scale.
* ``calibrated`` (3): an estimate informed by data (an accepted update in which the windows,
  not the prior, determined at least one parameter) whose offsets and scales are each known
  to UNPINNED_MG at 1 g (`unsettled`), and the self-watch has no objection.
* ``held`` (4): an estimate exists but no data informed it yet: the pre-calibration as given
  (a configured prior), or the prior again after a self-watch reset, until an accepted update
  observes a parameter; or data did not observe an offset or scale the prior does not pin
  (`Pipeline.unobserved`); or data observed one but do not know it to UNPINNED_MG yet
  (`Pipeline.converging`: the first minutes after a bootstrap or a reset); or a moment of
  doubt is not yet over (below).
* ``suspect`` (5): the self-watch's alarm (`Watch`): the estimator fitted an offset jump (a
  knock, or another sensor now under this id: held for JUMP_REPEAT_S), or the still windows
  contradicted the estimate beyond its uncertainty for a sustained time (a second jump
  within JUMP_REPEAT_S, or windows failing the norm gate for SUSPECT_AFTER_S) and the
  pipeline reset it: back to the prior with a buffer of the recent windows only (those since
  the first jump, or since the contradiction began), re-fitted at once; if the prior does
  not fit them either, no estimate and a bootstrap from them. It clears when the windows
  agree again (CLEAR_GOOD_WINDOWS in a row, after the alarm's hold).

Precedence: no estimate (uncalibrated, bootstrapping) before suspect before held.

0 (``not_recorded``) is the protobuf default: a recording made before statuses existed.

Besides the alarms above, two moments hold the status (`Watch.probation`, `Watch.gross`):

* A gross contradiction: a still window whose calibrated norm is further from 1 g than
  GROSS_MIN_MG and GROSS_SIGMAS x its predicted 1-sigma error (calibration, misfit and the
  window's noise) makes the output suspect from that window on (no sustained test first);
  it clears like any alarm (CLEAR_GOOD_WINDOWS agreeing windows after GROSS_HOLD_S).
* A moment of doubt (`Pipeline.doubt`: the device's clock restarted, the state came from a
  checkpoint): the output is held until still windows in PROBATION_WINDOWS orientation
  cells agree with the estimate (a gross contradiction among them: suspect). A port that
  opened again (`CalibrationNode.port_reopened`) or a gap in device time beyond GAP_S (the
  pipeline's own) holds it until one still window agrees (REOPEN_PROBATION_WINDOWS).

A calibration whose offsets or scales the data never observed (a wearer who never lies down:
the scale along the never-vertical axis) is ``held``, not calibrated, however long it runs;
the calibration state names the unobserved parameters (``unobserved``).

The predicted error (`predicted_sigma_mg`, `core.sigma`) is the 1-sigma length of the error of the
calibrated vector that the parameters' uncertainty causes: the estimate's covariance C_e
(Lötters eq. 11b) through the correction's Jacobian J = da/dp at each sample,
sigma_C^2 = trace(J C_e J^T), widened by what the model cannot explain (`RunningMisfit`: the still
windows' norm residual beyond what the sensor's noise and C_e explain, the buffer fit's
residual, the estimate's excess movement, and for a model without cross-axis terms what such
terms may err across gravity where the postures cannot show them, `misfit.unseen_cross_form`,
at the sample's own vector).
The sensor's own noise on the sample is not in it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from recal.core.buffer import Window, WindowBuffer, Windows, cell_of
from recal.core.effects import Covariates
from recal.core.misfit import ACROSS_SPHERE, CHANCE_SDS, excess_g2
from recal.core.model import SensorModel
from recal.core.pending import PendingCandidate
from recal.core.sigma import (  # the predicted error, importable from here too
    correction_jacobian,
    predicted_sigma_mg,
    sigma_form,
    sigma_one_mg,
)
from recal.core.triaxial import norm3

__all__ = ["CLEAR_AFTER_S", "CLEAR_GOOD_WINDOWS", "GAP_S", "GROSS_MIN_MG", "GROSS_SIGMAS",
           "JUMP_REPEAT_S", "NOT_FINITE_SIGMA_MG", "PROBATION_WINDOWS", "SUSPECT_AFTER_S",
           "UNPINNED_MG", "RunningMisfit", "Status", "Watch",
           "correction_jacobian", "offsets_and_scales", "predicted_sigma_mg", "refill",
           "sigma_form", "sigma_one_mg", "status_line", "unsettled"]


class Status(IntEnum):
    """Per-sample status of the calibrated output (module doc); values are the wire's."""

    NOT_RECORDED = 0
    UNCALIBRATED = 1
    BOOTSTRAPPING = 2
    CALIBRATED = 3
    HELD = 4
    SUSPECT = 5

    @property
    def label(self) -> str:
        return self.name.lower()


#: sigma of a sample published zeroed because its calibrated value was not finite: nothing
#: is known of it (a weight 1/sigma^2 of 0).
NOT_FINITE_SIGMA_MG = float("inf")

#: Two ways the still windows contradict the estimate beyond its uncertainty:
#: 1. The estimator fits an offset jump (`estimator._jump`: the newest windows each beyond 7
#:    sigma, Lötters eq. 14 over C_mu + B C_e B^T) and another within JUMP_REPEAT_S: a knock
#:    is one jump, after which the windows agree; a sensor whose gains differ too jumps again
#:    at a new posture (how soon: docs/performance.md, bench/status_watch.py). The status
#:    stays suspect that long after a first jump: until then the estimate may be a compromise
#:    between two sensors that fits the norms of the postures seen since.
JUMP_REPEAT_S = 1800.0
#: 2. The windows fail the norm gate (calibrated norm further than norm_tol_g from 1 g, or not
#:    finite), so they never reach the estimator: for SUSPECT_AFTER_S of device time, at least
#:    SUSPECT_MIN_BAD of them and at least half of the windows since the first.
SUSPECT_AFTER_S = 180.0
SUSPECT_MIN_BAD = 10
#: A contradiction ends after this many agreeing windows in a row (passing the norm gate);
#: a suspect status clears then, once its alarm's hold passed: JUMP_REPEAT_S after a first
#: jump, CLEAR_AFTER_S after a reset (the estimate is then this sensor's windows alone: long
#: enough for the wearer to show it new postures).
CLEAR_GOOD_WINDOWS = 10
CLEAR_AFTER_S = 600.0
#: Most windows the watch keeps from a contradiction, to re-fit them after a reset (bounded).
RECENT_MAX = 256
#: A still window contradicts grossly when its calibrated norm is further from 1 g than both
#: GROSS_MIN_MG and GROSS_SIGMAS x sqrt(sigma_C^2 + misfit + noise^2) (the window's own
#: sigma): the output is suspect from that window on, for GROSS_HOLD_S at least. 6 sigma,
#: not 10: sigma now carries what the model cannot explain, so a norm 6 sigma off is no
#: chance (Gaussian: ~1e-9); another sensor under the id 24 mg off at sigma 3 mg (7 sigma)
#: was calibrated until a later update at 10 (bench/sigma_honesty.py, docs/performance.md).
GROSS_MIN_MG = 20.0
GROSS_SIGMAS = 6.0
GROSS_HOLD_S = 0.0
#: After a moment of doubt, still windows in this many orientation cells must agree before
#: output is calibrated: the norm at one posture sees one direction of the offsets' error
#: (another sensor's offsets can be 100 mg off across gravity and agree in the norm).
PROBATION_WINDOWS = 3
#: After the device's data came back through a reopened port (unplugged and plugged in again:
#: perhaps another device under the id, with a clock of its own that need not restart), the
#: first still window must agree before output is calibrated again. One window, not
#: PROBATION_WINDOWS: a loose USB lead reopens many times a day, and three orientations cost
#: minutes of held output each time (docs/design.md, "a check after a port reopen").
REOPEN_PROBATION_WINDOWS = 1
#: A step in device time longer than this between two samples is a gap (`Pipeline`: a doubt
#: for REOPEN_PROBATION_WINDOWS from the sample after it): the device's data stopped, a radio
#: out of range or a link re-paired, time in which another device may have come under the id
#: without a port of the gateway closing. 2 s: 50 sample steps at 25 Hz, longer than a batch
#: of a working link takes to come, shorter than a re-pairing by hand.
GAP_S = 2.0
#: The misfit's running means weigh each still window by this (a memory of ~32 windows).
MISFIT_WEIGHT = 1.0 / 32.0
#: A window's squared residual enters the misfit's mean clipped at this many times the
#: variance expected of it (noise, C_e and the misfit so far), at least MISFIT_FLOOR_MG^2
#: (one window through a leak of the detector is no misfit; a growing effect doubles q
#: within a few windows all the same).
MISFIT_CLIP = 9.0
MISFIT_FLOOR_MG = 1.0
#: Of the residual's mean square, what chance allows above the expected one before any of it
#: counts as misfit (the relative sd of a mean of ~2/MISFIT_WEIGHT squares is ~0.18; 1.5 x
#: the expected is ~3 sd of it, `misfit.chance`): clean data leave q at 0, sigma as it was.
MISFIT_CHANCE = 1.5
#: The misfit on the output changes when it moved by more than this (relative, in sigma) and
#: MISFIT_STEP_MG: per window work, a few segments per batch.
MISFIT_STEP = 0.1
#: The residual the parameters in force leave on the buffer's windows (`RunningMisfit.fitted`)
#: counts beyond their noise and MISFIT_FIT_FLOOR_MG (a fit that good needs no widening).
MISFIT_FIT_FLOOR_MG = 0.5
#: The estimate's movement (`RunningMisfit.moved`): counted beyond MISFIT_MOVE_SDS of its sd, summed
#: over the last MISFIT_DRIFT_S of device time (decaying).
MISFIT_MOVE_SDS = 2.0
MISFIT_DRIFT_S = 600.0
MISFIT_STEP_MG = 0.05


@dataclass
class RunningMisfit:
    """What the model cannot explain, from the still windows' calibrated norms.

    Two witnesses. The buffer (windows of many postures, temperatures and supplies, hours
    apart) under the parameters in force at each accepted update, one set for all of them
    (not the estimator's own residual, whose offset rate and ageing follow a drifting effect
    and hide most of it): its norm residual's mean square beyond the windows' noise, q_f
    (`fitted`), is what one set of the model's parameters cannot explain across them (a
    temperature, a supply, a cross-axis term the model lacks): what `recal discover`'s
    held-out residual of the same model scores on the same windows (docs/design.md, "one
    misfit figure"). The norm sees the error along gravity only: the vector's error can be
    kappa x larger in variance (`misfit.across_factor` of the buffer's window directions at
    that update, `across`: 5 when they cover the sphere, up to ACROSS_MAX when they do not
    span): kappa x q_f, q_f counted beyond MISFIT_FIT_FLOOR_MG.

    And each still window (after the bootstrap) gives r = |a| - 1 g under the parameters in force
    when it came, and the variance e2 = noise^2 + sigma_C^2 / 3 the model expects of r: the
    window mean's noise (per-axis variance / n, over s0^2) and the radial share of the
    calibration's own (isotropic) error. Running means (weight MISFIT_WEIGHT per window) of
    min(r^2, MISFIT_CLIP x (e2 + q)) and of e2 give the misfit variance
    q = max(mean r^2 - MISFIT_CHANCE x mean e2, 0): the reduced chi-square of recent windows
    beyond chance, as a variance: what the estimate in force fails to explain now (an effect
    that changes faster than the re-fits follow). It errs across gravity too: kappa q.

    The third witness is the estimate's own movement: an estimate that keeps moving by more
    than its covariance allows chases an effect the model lacks, and lags it in the
    directions the current postures do not show. Its squared excess movement over the last
    MISFIT_DRIFT_S (how long a direction may go unobserved: a wearer keeps postures for
    minutes), m (`moved`), is that lag's variance.

    And what no residual can show: a model without cross-axis terms at postures that do not
    reveal them (near the axes) errs across gravity by as much as a prior on those terms
    allows, at each sample's own calibrated vector a: u(a) = a^T W a (`unseen_w`,
    `misfit.unseen_cross_form` of the buffer's directions at each accepted update; 0 for a
    model with them), a per-sample term the pipeline folds into the sigma form (not in
    `extra_mg2`).

    sigma^2 = sigma_C^2 + kappa (q + q_f) + m + u(a). Where the model fits, q, q_f and m stay
    at 0 (the residual within chance of the noise); u shrinks as the postures cover the
    sphere, and is least at the postures the buffer saw. u lies across gravity: the gross
    test on a window's norm leaves it out (`norm_mg2`).

    Attributes:
        r2_g2: running mean of the clipped squared residuals (g^2).
        e2_g2: running mean of the variance expected of them (g^2).
        n: windows seen (the first weigh more: a plain mean until 1/MISFIT_WEIGHT of them).
        said_mg2: the misfit's share of sigma^2 in force on the output (`restate`): it
            changes when the misfit moved by more than MISFIT_STEP, so a batch's samples
            take few values of it.
        fit_g2: the buffer's misfit under the last accepted update's parameters (`fitted`).
        across: kappa of the buffer's directions at the last accepted update (`fitted`).
        moved_mg2: how far the offsets and scales moved beyond what their covariance allows
            (mg at 1 g, squared), summed over the accepted updates with a decay of
            MISFIT_DRIFT_S of device time (`moved`); moved_at_us: the last accepted update.
        unseen_w: W (3 x 3, row by row, g^2 per g^2) of the floor for unseen cross-axis terms
            at the last accepted update (u(a) = a^T W a).
    """

    r2_g2: float = 0.0
    e2_g2: float = 0.0
    n: int = 0
    said_mg2: float = 0.0
    fit_g2: float = 0.0
    moved_mg2: float = 0.0
    moved_at_us: int | None = None
    across: float = ACROSS_SPHERE
    unseen_w: tuple[float, ...] = (0.0,) * 9

    @property
    def q_g2(self) -> float:
        """The misfit variance of the norm (g^2)."""
        # `misfit.excess_g2` in plain floats (it runs per window; numpy's per-call cost
        # dominated): the same arithmetic, and np.maximum(x, 0.0)'s result for -0.0 and NaN
        x = self.r2_g2 - self.chance * self.e2_g2
        return 0.0 if x <= 0.0 else float(x)

    @property
    def chance(self) -> float:
        """What chance allows the running mean of squares relative to the expected:
        MISFIT_CHANCE, or over the first windows (a plain mean of n) more (`misfit.chance`:
        one window 46 mg off at an expected 30 mg, right after a bootstrap, is no misfit)."""
        few = 1.0 + CHANCE_SDS * math.sqrt(2.0 / max(self.n, 1))
        return few if few > MISFIT_CHANCE else MISFIT_CHANCE

    @property
    def along_mg2(self) -> float:
        """What the model misses along gravity (mg^2), q + q_f: the mean square of the still
        windows' norm residual beyond their noise that one set of the model's parameters
        leaves on them (q_f: the buffer's, q: each window under the parameters in force
        before it came). The quantity `recal discover`
        scores (its held-out RMS of |a| - 1 g, which holds the noise too) and the replay
        summary says ("the model misses"): docs/design.md, "one misfit figure"."""
        return 1e6 * (self.q_g2 + self.fit_g2)

    @property
    def extra_mg2(self) -> float:
        """What the misfit adds to every sample's sigma^2 (mg^2): kappa (q + q_f) + m, the
        first term kappa x `along_mg2` (the vector errs across gravity too); the floor u(a)
        is per sample (`unseen_w`)."""
        return 1e6 * self.across * (self.q_g2 + self.fit_g2) + self.moved_mg2

    @property
    def unseen_g2(self) -> float:
        """The floor's most at any vector of 1 g (g^2): W's largest eigenvalue."""
        return float(np.linalg.eigvalsh(np.reshape(self.unseen_w, (3, 3)))[-1])

    @property
    def norm_mg2(self) -> float:
        """The misfit in force (mg^2), which holds nothing of what lies across gravity unseen
        (`unseen_w`): the norm of a still window shows none of that, so a gross
        contradiction is judged without it (else the floor would hide another sensor's norm
        24 mg off)."""
        return self.said_mg2

    @staticmethod
    def detect_g2(noise_g2: float) -> float:
        """The largest mean square a misfit can add to the buffer fit's residual unseen (g^2):
        what `fitted` does not count beyond the windows' noise (noise_g2: their mean variance)."""
        return (MISFIT_CHANCE - 1.0) * noise_g2 + (1e-3 * MISFIT_FIT_FLOOR_MG) ** 2

    def moved(self, excess_mg2: float, now_us: int) -> None:
        """An accepted update at now_us moved the offsets and scales by excess_mg2 (squared,
        mg at 1 g) beyond what their covariance allows."""
        if self.moved_at_us is not None and now_us > self.moved_at_us:
            self.moved_mg2 *= math.exp(-(now_us - self.moved_at_us) / (MISFIT_DRIFT_S * 1e6))
        if math.isfinite(excess_mg2):
            self.moved_mg2 += excess_mg2
        self.moved_at_us = now_us

    def fitted(self, residual_rms_g: float, noise_g2: float,
               across: float = ACROSS_SPHERE, unseen_w: np.ndarray | float = 0.0) -> None:
        """An accepted update: the rms of the buffer's norm residuals under its parameters
        (g), the mean noise variance of the buffer's window means (g^2), kappa of their
        directions and what terms the model lacks may err unseen at them
        (`misfit.unseen_cross_form`, 3 x 3; a number u: u at any vector of 1 g; 0: none)."""
        w = np.asarray(unseen_w, np.float64)
        w = w * np.eye(3) if w.ndim == 0 else w.reshape(3, 3)
        if np.isfinite(w).all():
            self.unseen_w = tuple(w.ravel().tolist())
        if math.isfinite(residual_rms_g) and math.isfinite(noise_g2):
            self.fit_g2 = float(excess_g2(residual_rms_g ** 2, MISFIT_CHANCE * noise_g2
                                          + (1e-3 * MISFIT_FIT_FLOOR_MG) ** 2))
        if math.isfinite(across):
            self.across = across

    def see(self, r_g: float, e2_g2: float) -> None:
        """One still window's residual r_g and its expected variance e2_g2 (g^2)."""
        cap = MISFIT_CLIP * max(e2_g2 + self.q_g2, (MISFIT_FLOOR_MG * 1e-3) ** 2)
        w = max(MISFIT_WEIGHT, 1.0 / (self.n + 1))
        self.r2_g2 += w * (min(r_g * r_g, cap) - self.r2_g2)
        self.e2_g2 += w * (e2_g2 - self.e2_g2)
        self.n += 1

    def restate(self) -> bool:
        """The misfit in force takes the current one if that moved by more than MISFIT_STEP
        (relative, in sigma) or MISFIT_STEP_MG; True if it did."""
        extra_mg2 = self.extra_mg2  # once: it is the same both times
        old, new = math.sqrt(self.said_mg2), math.sqrt(extra_mg2)
        if abs(new - old) <= max(MISFIT_STEP * old, MISFIT_STEP_MG):
            return False
        self.said_mg2 = extra_mg2
        return True

    def to_dict(self) -> dict:
        return {"r2_g2": self.r2_g2, "e2_g2": self.e2_g2, "n": self.n,
                "said_mg2": self.said_mg2, "fit_g2": self.fit_g2, "moved_mg2": self.moved_mg2,
                "moved_at_us": self.moved_at_us, "across": self.across,
                "unseen_w": list(self.unseen_w)}

    @classmethod
    def from_dict(cls, d: dict | None) -> RunningMisfit:
        if not d:
            return cls()
        return cls(float(d["r2_g2"]), float(d["e2_g2"]), int(d["n"]),
                   float(d.get("said_mg2", 0.0)), float(d.get("fit_g2", 0.0)),
                   float(d.get("moved_mg2", 0.0)),
                   None if d.get("moved_at_us") is None else int(d["moved_at_us"]),
                   float(d.get("across", ACROSS_SPHERE)), _unseen_w(d))


def _unseen_w(d: dict) -> tuple[float, ...]:
    """The floor's W from a checkpoint: "unseen_w", or an older one's single u at any
    orientation ("unseen_g2": W = u I)."""
    if "unseen_w" in d:
        return tuple(float(x) for x in d["unseen_w"])
    return tuple((float(d.get("unseen_g2", 0.0)) * np.eye(3)).ravel().tolist())


#: "calibrated" needs every offset and scale known to this at 1 g (sd of the estimate): one
#: the data did not observe and the prior does not pin (`Pipeline.unobserved`), or one the
#: data observed but not yet that well (`unsettled`), holds the status.
UNPINNED_MG = 5.0


def unsettled(model: SensorModel, cov: np.ndarray) -> tuple[str, ...]:
    """The offsets and scales whose sd (cov: the parameters' covariance) is worth more than
    UNPINNED_MG at 1 g (or is not finite): output is held, not calibrated, while any (the first
    updates of a bootstrap know them to 20-30 mg: sigma honest but far above the error)."""
    sd_mg = 1e3 * np.sqrt(np.clip(np.diag(cov), 0, None)) / model.s0
    return tuple(model.names[i] for i in offsets_and_scales(model)
                 if not sd_mg[i] <= UNPINNED_MG)


def offsets_and_scales(model: SensorModel) -> list[int]:
    """The indices of the model's offsets and scales in p."""
    return [i for kind in ("offset", "scale") if model.has(kind)
            for i in range(model.slice((kind, None)).start, model.slice((kind, None)).stop)]


def gross(r_g: float, sigma2_mg2: float) -> bool:
    """A still window's norm residual r_g beyond both GROSS_MIN_MG and GROSS_SIGMAS x its
    sigma (sigma2_mg2: its variance, mg^2), or not finite."""
    r_mg = abs(1e3 * r_g)
    if not math.isfinite(r_mg):
        return True
    return r_mg > GROSS_MIN_MG and r_mg > GROSS_SIGMAS * math.sqrt(max(sigma2_mg2, 0.0))


@dataclass
class Watch:
    """The self-watch's state: is the current contradiction (if any) sustained?

    Attributes:
        onset_us: device time of the first contradicting window of the current stretch
            (None: no contradiction going on).
        n_all, n_bad: windows since the onset, and how many of them contradicted.
        good_run: agreeing windows in a row (a stretch ends at CLEAR_GOOD_WINDOWS).
        suspect: the output is marked suspect (set at a trigger, cleared when windows agree).
        triggers: how many times the watch fired (each fires a reset).
        jump_us: when the estimator last fitted a new offset jump (None: none since a reset).
        alarm_us: device time until which an alarm holds the suspect status at least.
        recent: the windows since the onset (`buffer.Window`), at most RECENT_MAX,
            whatever the norm gate said of them: a reset re-fits them.
        probation: orientation cells whose still windows must still agree before output is
            calibrated (after a moment of doubt, `doubt`); agreed: the cells that did.
        calm_run: windows in a row that neither failed the norm gate nor contradicted
            grossly (a suspect status clears at CLEAR_GOOD_WINDOWS of them).
        misfit: what the model cannot explain (`RunningMisfit`).
        pending: a candidate model discovery proposed, neither adopted nor rejected yet
            (`core.pending`: sigma carries where the two disagree); a reset keeps it.
    """

    onset_us: int | None = None
    n_all: int = 0
    n_bad: int = 0
    good_run: int = 0
    suspect: bool = False
    triggers: int = 0
    recent: list[Window] | None = None
    jump_us: int | None = None
    alarm_us: int | None = None
    probation: int = 0
    misfit: RunningMisfit = field(default_factory=RunningMisfit)
    agreed: list[int] = field(default_factory=list)
    calm_run: int = 0
    pending: PendingCandidate | None = None

    def doubt(self, cells: int = PROBATION_WINDOWS) -> None:
        """A moment of doubt: still windows in ``cells`` orientation cells must agree (a
        probation already asking for more is kept as it is)."""
        if cells > self.probation:
            self.probation, self.agreed = cells, []

    def see(self, bad: bool, window: Window, grossly: bool = False,
            cell: int = -1) -> str | None:
        """One window in order (grossly: it contradicts grossly, `gross`); returns "trigger"
        when the contradiction became sustained, "clear" when a suspect status ends, "gross"
        when a gross contradiction made the status suspect now, "trusted" when a probation
        ended, else None."""
        t_us = int(window.t_us)
        said = None
        # a gross contradiction that passes the norm gate counts as agreeing for the
        # sustained test (which resets the estimate: the norm gate's alone), not for clearing
        self.calm_run = 0 if bad or grossly else self.calm_run + 1
        if grossly:
            self.probation, self.agreed = 0, []
            said = "gross" if self.alarm(t_us, GROSS_HOLD_S) else None
        elif not bad and self.probation and cell not in self.agreed:
            self.agreed.append(cell)
            self.probation -= 1
            said = "trusted" if not self.probation and not self.suspect else None
        if bad:
            self.good_run = 0
            if self.onset_us is None:
                self.onset_us, self.n_all, self.n_bad, self.recent = t_us, 0, 0, []
        else:
            self.good_run += 1
        if self.onset_us is not None:
            self.n_all += 1
            self.n_bad += bad
            assert self.recent is not None
            self.recent.append(window)
            if len(self.recent) > RECENT_MAX:
                del self.recent[0]
            if (t_us - self.onset_us >= SUSPECT_AFTER_S * 1e6 and self.n_bad >= SUSPECT_MIN_BAD
                    and 2 * self.n_bad >= self.n_all):
                return "trigger"
        if self.good_run >= CLEAR_GOOD_WINDOWS:
            self.onset_us, self.n_all, self.n_bad, self.recent = None, 0, 0, None
        if (self.suspect and self.calm_run >= CLEAR_GOOD_WINDOWS
                and (self.alarm_us is None or t_us >= self.alarm_us)):
            self.suspect = False
            return "clear"
        return said

    def alarm(self, t_us: int, hold_s: float = CLEAR_AFTER_S) -> bool:
        """Suspect from device time t_us on, for hold_s at least; True if it was not."""
        was, self.suspect = self.suspect, True
        self.alarm_us = max(self.alarm_us or 0, int(t_us + hold_s * 1e6))
        return not was

    def fired(self, t_us: int) -> list[Window]:
        """A reset at t_us: suspect from now, a new stretch; the windows to re-fit."""
        recent = self.recent or []
        self.suspect, self.alarm_us = True, int(t_us + CLEAR_AFTER_S * 1e6)  # a fresh start
        self.triggers += 1
        self.onset_us, self.n_all, self.n_bad, self.recent, self.good_run = None, 0, 0, None, 0
        self.jump_us, self.probation, self.agreed, self.calm_run = None, 0, [], 0
        self.misfit = RunningMisfit()  # measured under the estimate the reset drops
        return recent

    def jumped(self, step_us: int, now_us: int) -> str | None:
        """The estimator fitted a new offset jump at step_us (an accepted update at now_us):
        "reset" if it is a second one within JUMP_REPEAT_S of the first (another sensor under
        this id, another sensor's checkpoint: its gains differ too, so it jumps again at a new
        posture), "suspect" if the status becomes suspect now (held JUMP_REPEAT_S at least),
        else None (already suspect)."""
        first = self.jump_us
        if first is not None and step_us - first <= JUMP_REPEAT_S * 1e6:
            return "reset"
        self.jump_us = step_us
        return "suspect" if self.alarm(now_us, JUMP_REPEAT_S) else None

    def to_refit(self, buffered: Windows, now_us: int) -> list[Window]:
        """A reset at now_us (`fired`): the windows to re-fit, each once: the contradiction's,
        and after a jump the buffer's (``buffered``) since the first jump."""
        since = self.jump_us
        recent = self.fired(now_us)
        if since is not None:
            keep = buffered.t_us >= since
            recent = [Window(buffered.v[i], buffered.aux[i], int(buffered.t_us[i]),
                             int(buffered.n[i]), float(buffered.var[i]))
                      for i in np.flatnonzero(keep).tolist()] + recent
            recent = list({int(r.t_us): r for r in recent}.values())  # each window once
        return recent

    def to_dict(self) -> dict:
        return {"onset_us": self.onset_us, "jump_us": self.jump_us, "alarm_us": self.alarm_us,
                "n_all": self.n_all, "n_bad": self.n_bad, "good_run": self.good_run,
                "suspect": self.suspect, "triggers": self.triggers,
                "probation": self.probation, "agreed": list(self.agreed),
                "calm_run": self.calm_run,
                "misfit": self.misfit.to_dict(),
                "pending": None if self.pending is None else self.pending.to_dict(),
                "recent": None if self.recent is None else [
                    [list(map(float, w.v)), list(map(float, w.aux)), int(w.t_us), int(w.n),
                     float(w.var)] for w in self.recent]}

    @classmethod
    def from_dict(cls, d: dict | None) -> Watch:
        if not d:
            return cls()
        recent = d.get("recent")
        return cls(None if d.get("onset_us") is None else int(d["onset_us"]), int(d["n_all"]),
                   int(d["n_bad"]), int(d["good_run"]), bool(d["suspect"]), int(d["triggers"]),
                   None if recent is None else [_window(w) for w in recent],
                   None if d.get("jump_us") is None else int(d["jump_us"]),
                   None if d.get("alarm_us") is None else int(d["alarm_us"]),
                   int(d.get("probation", 0)), RunningMisfit.from_dict(d.get("misfit")),
                   [int(c) for c in d.get("agreed", ())],
                   int(d.get("calm_run", d.get("good_run", 0))),
                   PendingCandidate.from_dict(d.get("pending")))


def _window(w: Sequence) -> Window:
    """A recent window as a checkpoint holds it (its raw values as Python floats)."""
    return Window(list(map(float, w[0])), list(map(float, w[1])), int(w[2]), int(w[3]),
                  float(w[4]))


def refill(buffer: WindowBuffer, n_aux: int, model: SensorModel, p: np.ndarray,
           covariates: Callable[[np.ndarray, np.ndarray], Covariates], recent: list[Window],
           norm_tol_g: float | None, grid: int) -> int:
    """After a reset: the recent windows whose calibrated norm (parameters p) is within
    norm_tol_g of 1 g (None: all finite ones) into the buffer, each a slot of its own, oldest
    first; returns how many."""
    if not recent:
        return 0
    recent = sorted(recent, key=lambda r: r.t_us)
    m, k = len(recent), n_aux
    w = Windows(np.array([r.v for r in recent], float).reshape(m, 3),
                np.array([r.aux for r in recent], float).reshape(m, k),
                np.array([r.t_us for r in recent], np.int64),
                np.array([r.n for r in recent], np.int64),
                np.array([r.var for r in recent], float))
    a = model.correct(p, w.v, covariates(w.t_us, w.aux))
    norm = norm3(a)
    ok = np.abs(norm - 1.0) <= norm_tol_g if norm_tol_g is not None else np.isfinite(norm)
    dirs = a / np.where(norm > 0, norm, 1.0)[:, None]
    cells = cell_of(dirs, grid)
    for i in np.flatnonzero(ok).tolist():
        buffer.add(w.v[i].tolist(), w.aux[i].tolist(), int(w.t_us[i]), int(w.n[i]),
                   float(w.var[i]), dirs[i].tolist(), None, int(cells[i]))
    return int(ok.sum())


def status_line(d: dict) -> str:
    """How many samples went out with a status other than calibrated, said for a person."""
    by = d.get("samples_by_status") or {}
    others = ", ".join(f"{k} {v}" for k, v in by.items() if k not in ("calibrated",
                                                                        "not_recorded"))
    text = (f"{by.get('calibrated', 0)} samples out calibrated, {d['samples_not_calibrated']} "
            "with another status" + (f" ({others})" if others else ""))
    if d.get("samples_status_not_recorded"):
        text += (f"; {d['samples_status_not_recorded']} without a status (recorded before "
                 "statuses existed)")
    return text

"""Hindsight calibration: one fit on a whole recording's still windows, applied to all of it.

This is what the batch tools do (actipy, scikit-digital-health, GGIR and wristpy fit one
offset and gain per axis on a whole recording, then correct all of it), done with recal's
detector, windows and sensor model: any registered effect (cross-axis terms, a supply or
temperature channel, ...), and the parameters the poses cannot determine held at their start
and reported. The live service streams instead (`pipeline`: each sample corrected with what
was known when it arrived); this module is for a recording already on disk.

1. windows: `window_means.Windowing`, the live detector (Lötters eq. 1-2) and windowing;
2. the fit (`fit`): from an ellipsoid or sphere fit of the window means (`model_fit.start_params`),
   Lötters eq. 11a iterated to convergence (`estimator.solve`, the prior rows at the start
   values with the model's default spreads), over the parameters the poses determine (the
   others held at their nominal values, as the live core holds them), with no process
   noise: every window counts alike whatever its age. Windows whose corrected norm is
   further than norm_tol_g from 1 g (movement the detector let through, the live pipeline's
   norm gate) are dropped and the fit repeated until it keeps the same windows;
3. the correction (inverse of Lötters eq. 3) of every sample: `HindsightFit.correct`, with
   its predicted error: the parameters' covariance (Lötters eq. 11b) scaled by the fit's
   reduced chi-square, and what the model cannot explain there (`residuals.misfit`: the still
   windows' residual beyond their noise, pooled over the minutes around each sample, times
   the factor by which the error of the vector can exceed what the norm shows,
   `misfit.across_factor` of those windows' directions), so sigma grows where the residual
   grows (`HindsightFit.sigma_mg`); where that residual is far above the noise the samples
   are suspect (`HindsightFit.poor`).

Without a model given, `discover_and_calibrate` first selects the effects as `recal discover`
does (`discovery.discover` on the same windows, the same rule), then fits the model found.

Why and how it compares with the batch tools: docs/design.md and docs/performance.md
("Calibration with hindsight").
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from recal.core.batch_windows import WindowsFn, in_order
from recal.core.bootstrap import off_by
from recal.core.buffer import Windows
from recal.core.discovery import DiscoveryConfig, DiscoveryResult, discover
from recal.core.discovery_data import DiscoveryData, data_from_windows
from recal.core.effects import Covariates
from recal.core.model import AffineCorrection, SensorModel
from recal.core.model_fit import FitConfig, fit_model, free_params, nominal, start_params
from recal.core.pipeline_config import PipelineConfig
from recal.core.quantization import rounding_g2
from recal.core.residuals import MisfitProfile, misfit
from recal.errors import InputError
from recal.samples import RawBatch

__all__ = ["SUSPECT_EXCESS_G", "HindsightFit", "calibrate", "discover_and_calibrate", "fit"]

#: Most fits of `fit`: each drops the windows the one before put beyond norm_tol_g.
MAX_PASSES = 5
#: A local residual this far beyond the noise (along gravity, g) marks the samples there
#: suspect: the model misses an effect of at least that size there (a clean fit leaves
#: well under 1 mg).
SUSPECT_EXCESS_G = 0.005


@dataclass(frozen=True, eq=False)
class HindsightFit:
    """A recording's calibration with hindsight.

    Attributes:
        model, p: the sensor model and its fitted parameters (raw units, as `Estimate.p`).
        cov: their posterior covariance (Lötters eq. 11b; the prior's for held ones).
        free: the parameters the poses determined; the others were held at their start.
        t0_us: origin of the model's "time" covariate (the recording's first sample).
        windows: windows fitted; dropped: windows left out (movement, beyond norm_tol_g).
        residual_rms_mg: RMS of 1 g - |a| over the windows fitted.
        misfit: the fitted windows' residual beyond their noise, in time (`residuals.misfit`;
            None: not measured).
    """

    model: SensorModel
    p: np.ndarray
    cov: np.ndarray
    free: np.ndarray
    t0_us: int
    windows: int
    dropped: int
    residual_rms_mg: float
    misfit: MisfitProfile | None = None

    @property
    def chi2(self) -> float:
        """Reduced chi-square of the fit (1 where the model explains the windows)."""
        return self.misfit.chi2 if self.misfit is not None else 1.0

    @property
    def poor(self) -> bool:
        """The fit leaves a residual well above the noise somewhere (SUSPECT_EXCESS_G)."""
        return self.misfit is not None and self.misfit.max_excess_g > SUSPECT_EXCESS_G

    def sigma_mg(self, t_us: np.ndarray, sigma_p_mg: np.ndarray) -> np.ndarray:
        """Predicted 1-sigma error (mg) of samples at t_us whose error from the parameters'
        covariance alone is sigma_p_mg: that scaled by the reduced chi-square (when above
        1), with the misfit's variance of the vector added (`MisfitProfile.vector_var_g2`:
        the excess beyond the noise times the factor by which the vector's error can exceed
        the norm's, locally or over the whole recording, whichever is larger)."""
        s2 = np.asarray(sigma_p_mg, np.float64) ** 2 * max(1.0, self.chi2)
        if self.misfit is not None:
            s2 = s2 + 1e6 * self.misfit.vector_var_g2(t_us)
        return np.sqrt(s2)

    def suspect(self, t_us: np.ndarray) -> np.ndarray:
        """Which samples lie where the local excess is beyond SUSPECT_EXCESS_G."""
        if self.misfit is None:
            return np.zeros(len(t_us), bool)
        return self.misfit.at(t_us) > SUSPECT_EXCESS_G

    def correct(self, b: RawBatch, out: np.ndarray | None = None) -> np.ndarray:
        """Raw samples -> acceleration in g (N,3), into ``out`` if given (a recording's output
        array, batch by batch): one small matrix product when the model allows it
        (`SensorModel.affine`: the same to rounding, several times faster), else the model's
        chain of stages."""
        aff = self._affine
        cov = (Covariates.from_samples(b.t_us, b.aux, b.aux_names, self.t0_us)
               if aff is None or aff.divisors else None)
        if aff is not None:
            return aff(b.v, cov, out)
        a = self.model.correct(self.p, b.v, cov)  # type: ignore[arg-type]
        if out is None:
            return a
        out[...] = a
        return out

    @functools.cached_property
    def _affine(self) -> AffineCorrection | None:
        return self.model.affine(self.p)

    @property
    def held(self) -> tuple[str, ...]:
        """Parameters the recording's poses could not determine (held at their start)."""
        return tuple(n for n, f in zip(self.model.names, self.free, strict=True) if not f)


def fit(windows: Windows, aux_names: tuple[str, ...], t0_us: int, model: SensorModel,
        norm_tol_g: float = 0.1, step_raw: np.ndarray | None = None,
        data: DiscoveryData | None = None) -> HindsightFit:
    """The model fitted to a recording's window means (module doc, step 2); step_raw: the
    sensor's step per axis (raw units; None or inf: unknown), whose rounding the means keep
    where the noise does not dither it (`quantization.mean_floor_g2`). data: the windows'
    `data_from_windows`, when the caller has it."""
    if data is None:
        data = data_from_windows(windows, aux_names, t0_us)
    dropped = data.dropped
    if off_by(data.zero, data.s0, np.zeros(3), model.s0):  # s0 a first guess (`calibrate`)
        model = SensorModel(model.effects, data.s0, model.spreads)
    p = start_params(model, data)
    # what the poses cannot determine stays at the model's nominal value (the datasheet, as
    # in the live core; the offsets at the data's zero-g), not at the start's: an ellipsoid
    # or sphere fit to a cap of orientations trades the unseen axis's scale against its
    # offset almost freely
    held = ~free_params(model, p, data)
    p[held] = nominal(model, data)[held]
    cfg = FitConfig()
    keep = np.ones(len(data), bool)
    for _ in range(MAX_PASSES):
        fitted = keep  # the windows of this fit: what the report counts
        res = fit_model(model, p, data.subset(fitted), cfg)
        xi = model.residual(res.p, data.windows.v, data.cov)
        keep = np.abs(xi) <= norm_tol_g
        if np.array_equal(keep, fitted) or not keep.any():
            break
    xi_fitted = xi[fitted]
    w = data.windows
    a = model.correct(res.p, w.v, data.cov)[fitted]  # directions: `misfit.across_factor`
    # the noise left in a window mean, per axis and so along gravity: var / n of its samples,
    # and the rounding no noise averages away
    noise2 = (w.var[fitted] / np.maximum(w.n[fitted], 1) / model.s0**2
              + rounding_g2(w.var[fitted], model.s0, step_raw))
    return HindsightFit(model, res.p, res.cov, res.free, int(t0_us), int(fitted.sum()),
                        dropped + int((~fitted).sum()),
                        1e3 * float(np.sqrt(np.mean(xi_fitted**2))) if len(xi_fitted) else 0.0,
                        misfit(xi_fitted, noise2, w.t_us[fitted], a=a))


def calibrate(batches: Callable[[], Iterable[RawBatch]], model: SensorModel,
              cfg: PipelineConfig, *, windows_of: WindowsFn | None = None) -> HindsightFit:
    """Fit a recording read batch by batch (``batches()``: one pass over it, or two; or its
    windows as ``windows_of`` finds them, `batch_windows.WindowsFn`) with hindsight. The
    detector runs in units of model.s0 raw per g; when the windows show zero-g far from 0 or
    the scale far from s0 (`bootstrap.zero_and_scale`: an analog part on an unsigned ADC, s0
    a first sample's norm), once more centred at the zero-g found and in its units, and the
    model's s0 becomes that scale."""
    find = windows_of or in_order(batches)
    windows, aux_names, t0_us, step = _windows(find, cfg, model, model.s0, None)
    data = data_from_windows(windows, aux_names, t0_us)
    if off_by(data.zero, data.s0, np.zeros(3), model.s0):
        model = SensorModel(model.effects, data.s0, model.spreads)
        windows, aux_names, t0_us, step = _windows(find, cfg, model, data.s0, data.zero)
        data = data_from_windows(windows, aux_names, t0_us)
    return fit(windows, aux_names, t0_us, model, cfg.norm_tol_g, step, data)


def discover_and_calibrate(batches: Callable[[], Iterable[RawBatch]], s0: float,
                           cfg: PipelineConfig, dcfg: DiscoveryConfig | None = None, *,
                           windows_of: WindowsFn | None = None,
                           beside: Beside | None = None
                           ) -> tuple[HindsightFit, DiscoveryResult | str]:
    """`calibrate` of the model `discovery.discover` selects on the recording's windows (from
    offsets and gains at s0 raw units per g, as `recal discover`): the windows once (twice for
    an analog part, as `calibrate`), discovery on them, one fit of the model it found. Where
    discovery cannot score (too few windows, no pose two blocks share), the fit of offsets and
    gains, and why in place of the discovery.

    beside: how the fit of offsets and gains alone (discovery's start, and its answer on most
    recordings) is made while discovery runs (`Beside`; None: only if discovery keeps it)."""
    base = SensorModel.diagonal(s0)
    find = windows_of or in_order(batches)
    windows, aux_names, t0_us, step = _windows(find, cfg, base, s0, None)
    data = data_from_windows(windows, aux_names, t0_us)
    if off_by(data.zero, data.s0, np.zeros(3), s0):
        windows, aux_names, t0_us, step = _windows(find, cfg, base, data.s0, data.zero)
        data = data_from_windows(windows, aux_names, t0_us)
    plain = SensorModel.diagonal(data.s0)  # what discovery starts from (`discover`)
    plain_fit = (beside or _when_asked)(
        lambda: fit(windows, aux_names, t0_us, plain, cfg.norm_tol_g, step, data))
    try:
        found: DiscoveryResult | str = discover(data, cfg=dcfg or DiscoveryConfig())
    except InputError as exc:
        found = str(exc)
    model = found.model if isinstance(found, DiscoveryResult) else base
    if model.to_dict() == plain.to_dict():
        return plain_fit(), found
    return fit(windows, aux_names, t0_us, model, cfg.norm_tol_g, step, data), found


#: Starts work and gives what returns its result when called: the work done then
#: (`_when_asked`), or meanwhile on another thread (the shell's choice: `recal hindsight`).
Beside = Callable[[Callable[[], "HindsightFit"]], Callable[[], "HindsightFit"]]


def _when_asked(work: Callable[[], HindsightFit]) -> Callable[[], HindsightFit]:
    return work


def _windows(find: WindowsFn, cfg: PipelineConfig, model: SensorModel, s0: float,
             zero: np.ndarray | None) -> tuple[Windows, tuple[str, ...], int, np.ndarray]:
    """The recording's kept windows by the detector in units of s0, zero-g `zero` off, and
    the sensor's step as the detector learned it."""
    sums, aux_names, t0_us, step = find(cfg, model, s0, zero)
    if aux_names is None or t0_us is None:
        raise InputError("a recording needs samples to calibrate")
    if not len(sums):
        raise InputError("no quasi-static window in the recording: nothing to calibrate on")
    return sums.means()[0], aux_names, t0_us, step

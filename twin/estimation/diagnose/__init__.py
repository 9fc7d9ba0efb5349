"""Diagnose what a simulation gets wrong: name the physical cause, extend the model, measure the gain.

The method (``twin diagnose DATA --model NAME``, any registered model):

1. **Split** every record: the first ``1 - holdout`` (75 %) is fitting data, the
   rest is held out; held-out figures come from simulating the whole record
   with the fitted parameters and scoring only its tail.
2. **Fit the nominal model** (its phenomenological parameters free) by output
   error, under the loop's timing (``--controller``/``--intersample``).
3. **Noise model and one-step-ahead prediction errors** (:mod:`twin.estimation.noise_model`):
   output-error residuals of a closed loop whose controller reads the noisy
   measured displacement are coloured even when the model is exact (the
   sensor noise goes round the loop), and a sensor may itself be coloured.  An
   autoregression per output (order by AIC, raised along the grid while its
   errors stay materially predictable; innovations correlated across outputs)
   is fitted to the residuals on the fitting data; the residuals filtered by
   it are normalised innovations, one-step-ahead prediction errors.  Every
   statistic below is computed on them (Box-Jenkins style: output-error model,
   fitted noise model).
4. **Adequacy** of a model: its innovations are white (Ljung-Box per output,
   degrees of freedom reduced by the autoregression's order; a significant
   dependence counts only when the errors' own past predicts over 1 % of
   their variance beyond chance, ``WHITE_R2``) and the held-out
   innovations are no larger than those on the fitting data (a drift, or an
   error the fit bent the parameters around, shows there), and they do not
   follow the exogenous drive (``x_ref``; regressed on its increments at lags
   0-50 ms: significant, and explaining over 1 % of an output's innovation
   variance beyond chance) - an autoregression can soak up a deterministic
   error such as a resonance, an exogenous drive it cannot explain away;
   Bonferroni over the tests.  Loop noise and coloured sensor noise are not
   model errors.
5. **Screen the catalogue** with a score (Lagrange-multiplier) test in one
   batched simulation per record: the model at the estimate, at a step of
   every free parameter (Jacobian ``J``) and at probes of every candidate
   effect (a small step of each of its parameters away from neutral, plus
   secants to a few plausible magnitudes where the derivative at neutral
   vanishes; a limit such as the spool's stroke is probed at levels the
   record reaches: quantiles of the limited state's magnitude).  Residuals, ``J`` and the probe sensitivities ``s`` are
   whitened by the current noise model; with ``s_perp`` = ``s`` with the span
   of ``J`` projected out and ``g_t`` the per-sample score ``s_perp r``,

       LM = (sum g_t)^2 / (N * long-run variance of g)      (Newey-West),

   chi-square(1) when the effect is absent, even if whitening left some
   colour.  Each probe is also scored with the best directions of the
   ``CONDITION_ON`` strongest other effects projected out (one un-modelled
   effect can turn another's one-sided score to 0: a force offset's drift
   hides a dry friction), the larger kept.  An effect's p-value is its best probe's times its number of
   probes; the effects' p-values are Holm-corrected over the catalogue.  One-
   sided effects (a friction, a stroke limit) score 0 when the residual
   points the wrong way.  Nothing passes: nothing is fitted.  An effect that
   a free nominal parameter mimics (``Effect.mimicked_by``: a position sensor
   gain is a Cd change while Cd is free) is not screened; the diagnosis says
   so (``not_testable``) and how to test it (hold that parameter at a
   commissioned value).
6. **The loop's timing** (``controller_rate``): the alternative timings (a
   continuous controller, a digital one 2, 5, 10 times faster than the log)
   are simulated at the current estimates; the best is refitted, then the
   continuous one from its estimates (the nominal estimates are bent to the
   assumed timing, so the closest alternative scores best at them even when
   the loop is analog), then any other that scores lower at the best refit's
   estimates; the best refit is judged by the same tests as an effect,
   counted as one parameter.
7. **Fit the promising extensions** (nominal free parameters plus the
   effect's own) from the current estimates and from the configured
   baseline (nominal or commissioned values), the effect's starts across its
   physical range; a model simulated open loop is refitted over a growing
   horizon (``GROW_FRACTION``); the better refit by held-out error is kept.
   **Decide** by one criterion for every kind of name (an effect, a pair, a
   timing): accepted when its likelihood-ratio test on the whitened
   residuals (``LR = C0 - C1``, the innovations' sums of squares under the
   current noise model, chi-square(df)) is significant after a Holm
   correction over the catalogue, its (whitened) AICc is lower, its held-out
   gain - the relative reduction of the held-out innovations' sum of squares
   - is significant against the noise (a Diebold-Mariano-type test on the
   relative scale, HAC variance, one-sided at ``HOLDOUT_LEVEL``:
   :func:`.adequacy._holdout_test`), and its parameters lie within 10 times
   the effect's typical deviation from neutral.  While the extended model
   stays inadequate it must remove the majority (``min_share``) of the
   current model's simulation misfit above the noise floor (whole records).  The
   effect's own signature
   must be where the residuals have it (:func:`.naming._signature`): the
   errors it leaves are regressed on its signature led and lagged by 1-16
   samples; when that is significant and explains again over half of its
   gain (``1 - min_share``), it is not named - an effect standing in for an
   error of other dynamics (a transducer's lag taken for a friction) leaves
   exactly such a misplaced copy of its signature.  Candidates whose screen
   LM is below a tenth of an accepted extension's LR are not fitted.  The
   lowest AICc among accepted ones wins; the screen is run again on the
   extended model (greedy).  When no single effect passes but two are
   significant, the pair is fitted together and judged the same way, each
   significant within the pair.
8. **Verdict**: ``causes`` are the accepted effects; ``unexplained`` is true
   when the final model is not adequate (step 4): "explained", "partly
   explained" (named, a significant part left), "unexplained" (no name) or
   "adequate" (nothing to name); the residual signature is
   shown instead of a forced name.

:func:`diagnose` returns a :class:`Diagnosis`; the command line is
:mod:`twin.commands.diagnose`, the plots :func:`twin.reports.plots.diagnosis_plots`.

Modules, one concept each: :mod:`.constants` (significance levels, rules and tuned numbers with their
derivations), :mod:`.data` (the records, their split, a model state, simulations), :mod:`.adequacy` (the noise
model's use: prediction errors, adequacy tests, likelihood-ratio and held-out gains), :mod:`.screen` (the score
tests), :mod:`.timing` (the loop's timing search), :mod:`.extend` (fitting an extension), :mod:`.naming` (the
naming rules), :mod:`.results` (screen rows, trials, the :class:`Diagnosis`), :mod:`.search` (the greedy search).
"""

from typing import TYPE_CHECKING, Any

from twin.estimation.diagnose.constants import (ALPHA, CONTROLLER_RATE, FORCE_EFFECTS, INPUT_INTERSAMPLE, MIN_SHARE,
                                                SIGNATURE_AXIS, TIMING_EFFECTS)

if TYPE_CHECKING:
    from twin.estimation.diagnose.data import ModelState, holm
    from twin.estimation.diagnose.adequacy import _gain
    from twin.estimation.diagnose.naming import _implausible
    from twin.estimation.diagnose.results import Diagnosis, ScreenRow, Trial
    from twin.estimation.diagnose.screen import screen
    from twin.estimation.diagnose.search import diagnose

#: the package's names imported on first use: a fit's adequacy test (:mod:`.check`) loads its own modules only,
#: not the search, the screen and their statistics
_LAZY = {"ModelState": "data", "holm": "data", "_gain": "adequacy", "_implausible": "naming",
         "Diagnosis": "results", "ScreenRow": "results", "Trial": "results", "screen": "screen",
         "diagnose": "search"}


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    for n, mod in _LAZY.items():  # all at once: a submodule's import binds its name (screen) to the module
        globals()[n] = getattr(importlib.import_module(f"{__name__}.{mod}"), n)
    return globals()[name]


__all__ = ["ALPHA", "CONTROLLER_RATE", "FORCE_EFFECTS", "INPUT_INTERSAMPLE", "MIN_SHARE",
           "SIGNATURE_AXIS", "TIMING_EFFECTS", "Diagnosis", "ModelState", "ScreenRow", "Trial",
           "_gain", "_implausible", "diagnose", "holm", "screen"]

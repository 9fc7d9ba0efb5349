"""The filter's vocabulary and the layout of the arrays it carries: statuses, guard codes, sensor statuses, the
guard's settings (``cfg``), the carried float state (``fs``) and the per-output state (``ch``)."""

from __future__ import annotations

#: largest standard deviation (log units) the parameter random walk grows a parameter's uncertainty to
PARAM_STD_CAP = 1.0
STATUS = ("ok", "gated", "repaired_covariance", "stale_input", "frozen", "gap", "reinitialised", "recovered",
          "sensor_fault")
(ST_OK, ST_GATED, ST_REPAIRED, ST_STALE, ST_FROZEN, ST_GAP, ST_REINIT, ST_RECOVERED,
 ST_SENSOR) = range(len(STATUS))
#: why the drift test holds its evidence on a sample (0: it need not)
GUARD = ("consistent", "settling", "inconsistent_nis", "inconsistent_colour", "sensor_fault", "diverged")
G_OK, G_SETTLE, G_NIS, G_COLOUR, G_SENSOR, G_DIVERGED = range(len(GUARD))
#: sensor status per output
SENSOR = ("ok", "noisy", "stuck", "clipped", "offset", "wrong_unit", "missing")
S_OK, S_NOISY, S_STUCK, S_CLIPPED, S_OFFSET, S_UNIT, S_MISSING = range(len(SENSOR))

#: guard / detector settings (array ``cfg``), in this order (``twin.online.tracker.DEFAULT_GUARD`` names them)
CFG_NAMES = ("nis_clip", "nis_hi", "rho_hi", "tau_guard", "div_nis", "tau_div", "settle_s", "checkpoint_s",
             "inflate", "gap_max", "tau_noise", "adapt", "noisy_factor", "outlier_nu", "offset_n", "stuck_n",
             "clear_n", "z_pin", "sig_lo", "sig_hi", "a_max", "warm_s", "central_mean", "noise_share")
(C_NIS_CLIP, C_NIS_HI, C_RHO_HI, C_TAU_GUARD, C_DIV_NIS, C_TAU_DIV, C_SETTLE_S, C_CK_S, C_INFLATE, C_GAP_MAX,
 C_TAU_NOISE, C_ADAPT, C_NOISY, C_OUT_NU, C_OFF_N, C_STUCK_N, C_CLEAR_N, C_ZPIN, C_SIG_LO, C_SIG_HI,
 C_A_MAX, C_WARM_S, C_CENTRAL, C_NSHARE) = range(len(CFG_NAMES))
N_CFG = len(CFG_NAMES)
#: carried float state (array ``fs``); the model's controller memory follows from ``F_CTRL``
(F_NIS_EMA, F_NIS_FAST, F_SETTLE, F_CK_T, F_T, F_HAVE_PREV, F_U1, F_U2, F_R1, F_R2, F_XM1, F_EXC0, F_EXC1,
 F_EXC2, F_UPREV_OK, F_GATED_RUN, F_RECOVERIES, F_REINITS, F_CK_OK) = range(19)
F_CTRL = 19
#: per-output carried state (array ``ch [q, N_CH]``)
(H_SIG, H_A, H_C, H_R1, H_NU_PREV, H_LAST_RAW, H_RUN_SAME, H_OUT_RUN, H_CLEAR_RUN, H_STATUS, H_UNIT_RUN,
 H_SIG_NOM, H_R_FLOOR, H_HAVE_NU, H_EXT) = range(15)
N_CH = 15

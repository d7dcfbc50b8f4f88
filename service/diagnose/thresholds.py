"""The diagnosis's decision thresholds and numerical limits, in one table, each with its reason.

Statistical thresholds carry their source; the others are numerical limits of a search or an
approximation, with what they bound. Where a value is used is named beside it.
"""

# -- adding an effect and ranking candidates (:mod:`.search`) ------------------------------------------------
MAX_EFFECTS = 5           # effects the model lacks one diagnosis adds at most (``--max-effects``; refits of
                          # the model's own effects are not counted: diagnose._spent). A real IMU's model
                          # can lack a quantizer, a line, a flicker bias, a walk and its integral's white
                          # noise; the search stops earlier when nothing passes THRESHOLD
THRESHOLD = 10.0          # Delta BIC to add an effect: "very strong" evidence (Kass & Raftery 1995;
                          # BIC: Schwarz 1978)
CHIBAR2_95 = 2.706        # 95 % point of 1/2 chi2_0 + 1/2 chi2_1: a parameter whose null value is on
                          # its boundary (Self & Liang 1987), as in the nested pairs Search.choice ranks
TIE = 2.0                 # within which candidates count as equally supported (ranking units: Search.choice,
                          # or Delta BIC: 2 ln B below 2 is "not worth more than a bare mention", Kass &
                          # Raftery 1995)
EXACT_TIE = 0.5           # ... and within which they are the same fit (chain order decides)
DISTINCT_Z = 1.96         # a likelihood ratio this many of its standard deviations tells two fits apart
                          # (two-sided 95 % normal point)
SLOW_DRIFT = 10.0         # actuator AR(1) this many plant time constants slow: a drift (Search._drift_as_bias)
HARMONICS = 7             # a residual line at up to the 7th harmonic of a command line is the mean response's

# -- profile intervals (:mod:`.intervals`, :mod:`.inner`) ----------------------------------------------------
CHI2_95 = 3.841           # chi2_1 95 % point: two-sided profile intervals (Wilks 1938)
UNBOUNDED = 1e-4          # a profile's end this far from the estimate (ratio): the data do not bound it

# -- the likelihood (:mod:`.data`, :mod:`.evaluator`, :mod:`.hypotheses`) ------------------------------------
REL_BW = 0.01             # frequency groups: at most 1 % of their frequency wide (Whittle on group means)
LINE_SHARE = 0.01         # a command line carries at least 1 % of the command's power (Data.command_lines),
COMB_LINES = 20           # ... and a command with more such lines is a comb (a repeated chirp): none
GRID_TOL = 1e-6           # values within GRID_TOL * step of the grid count as on it
QUANT_LAGS = 8192         # lags of the quantizer's correlated error kept in the likelihood, unless ...
QUANT_TAIL = 1e-4         # ... it is still above this (relative) in their last quarter: then every lag
QUANT_SLOPE_MAX = 7.0     # 2 pi^2 V_d / step^2 above this (e^-7 ~ 1e-3): the error's decorrelation is negligible
BLIND = 1e-30             # a source whose part is below this share of the data's power: not seen (:class:`.inner.Inner`)

# -- the fits' searches (:mod:`.hypotheses`) -----------------------------------------------------------------
MAX_SHIFTS = 4            # a local shape search may move its bracket this many times (Hypotheses._search)
MORE_ROUNDS = 2           # extra rounds a joint search may take while a round still gains > 1 in l
QUANT_ROUNDS = 3          # refits of the variances with the quantizer's part from the fitted ones

# -- the sandwich variance (:mod:`.sandwich`) ----------------------------------------------------------------
SANDWICH_BLOCKS = 256     # block sums for the long-run variance of the score (Kuensch 1989)
SANDWICH_BLOCK_MIN = 64   # samples per block at least

# -- tone lines (:mod:`.tones`) ------------------------------------------------------------------------------
TONE_SIDE = 25            # bins either side of a tone candidate that give the data's own background
TONE_MIN_BINS = 5         # ... of which at least this many below it (a line needs a background on both sides)
                          # and twice as many in all (near Nyquist the side above is short)

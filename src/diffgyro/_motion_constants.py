"""The numbers of the judgement of rest (:mod:`diffgyro.motion`, docs/rest.md): each rule's
threshold, window and cap, with why it has its value. One place for the rule book: the
check, its judgement of the windows (:mod:`diffgyro._motion_host`,
:mod:`diffgyro._judgement_pass`) and the host's search for stretches of rest
(:mod:`diffgyro._rest_stretches`) read them here."""

from __future__ import annotations

import math

#: Earth's rotation rate (rad/s): the gyro's floor on a window-mean deviation.
EARTH_RATE = 7.292115e-5
#: The accelerometer's floor on a window-mean deviation (m/s², about 0.2 mg).
ACCEL_FLOOR = 2e-3
#: Deviations of a window mean, in its own noise, above which the window moves.
K_SIGMA = 6.0
#: Quantile of the windows' local noise taken as the rest noise.
REST_QUANTILE = 0.1
#: Quantile of the windows' half-window differences that gives a window mean's rest noise.
HALF_QUANTILE = 0.2
#: Window length (s) and baseline block (s) aimed at.
WINDOW_S = 0.25
BLOCK_S = 30.0
#: Most windows per device in a first look: a long recording at rest is shown at rest in
#: longer windows (the work on the windows then stays below the pass over the samples);
#: one that moved, or whose longer windows cannot show a turn of :data:`MAX_RESOLUTION`,
#: is judged again in the windows of its rate (:func:`diffgyro.motion.motion_check`).
MAX_WINDOWS = 512
#: A recording moved where a run of its moving windows reached this many times the
#: threshold (at any moving fraction), or gravity tilted by :data:`MIN_TILT` within a
#: stretch between moves. A slow unexplained change of the bias (a supply or duty step)
#: leaves the baseline by a few thresholds, and for long enough it adds up to a degree;
#: a turn by hand or vehicle leaves it by hundreds.
MIN_PEAK_RATIO = 10.0
MIN_TILT = math.radians(0.5)
#: The coarsest resolution (rad) at which a recording can be called at rest: a window at
#: the recording's rest noise must show a turn of this angle. A recording that cannot (too
#: noisy, too slowly sampled, or with no quiet part, whose own motion sets its noise) is
#: ``unverified``, never at rest.
MAX_RESOLUTION = math.radians(1.0)
#: Fewest valid windows a judgement needs (the rest noise is a quantile over them).
MIN_WINDOWS = 16
#: A window's noise may raise its threshold (vibration) at most this many times.
LOUDER_CAP = 8.0
#: Windows read for the rest noise's quantiles, and per baseline block for its median.
QUANTILE_WINDOWS = 512
BLOCK_WINDOWS = 16
#: Fastest change of a bias at rest (rad/s per s): a fast warm-up's (0.5 mrad/s/°C at
#: 0.1 °C/s). Two stretches of rest
#: either side of a motion whose rates differ by more than this allows (and their noise)
#: are not both rest: one of them spins (:func:`diffgyro._rest_stretches.rest_stretches`).
BIAS_SLEW = 5e-5
#: Gravity's change that a stretch of rest may not show (m/s²: a tilt of half a degree),
#: over chunks of this many windows (slow enough that a bias's thermal drift shows
#: nothing), and the fewest windows of a stretch of rest between two moves.
TILT_FLOOR = 9.80665 * math.sin(math.radians(0.5))
STRETCH_CHUNK = 32
MIN_STRETCH = 4
#: Levels held at least this share as long as the longest are candidates for the rest.
REST_SHARE = 0.5
#: The largest rate a gyro's bias reaches (rad/s, about 29 °/s: beyond the zero-rate
#: offsets that consumer MEMS datasheets allow); a level above it is a turn.
MAX_BIAS = 0.5
#: Groups of at most this many samples (devices × samples) are checked at a bucketed
#: shape (devices to :func:`~diffgyro.data.device_bucket`, windows to a power of two of
#: baseline blocks).
PAD_SAMPLES = 1 << 21

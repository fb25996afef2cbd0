//! Clock sync: estimating an MCU's clock from the host's system time.
//!
//! Each `get_clock` query is written at system time `s` and answered at `r`; the MCU read its
//! clock (`c`) somewhere in between. The sample's time is the midpoint `t = (s + r)/2`, so the
//! read time is known within ±rtt/2 whichever way the round trip was lopsided. An
//! exponentially weighted linear regression tracks the means and the (co)variance of `(t, c)`:
//!
//! ```text
//! dt = t − t̄;  t̄ += α·dt;  var_t = (1−α)·(var_t + α·dt²)
//! dc = c − c̄;  c̄ += α·dc;  cov   = (1−α)·(cov + α·dt·dc)
//! freq = cov / var_t            (ticks per system second)
//! ```
//!
//! and the published mapping is `clock(T) = c̄ + (T − t̄)·freq`. The decay is `α = 1/30` per
//! regular query (0.98 s apart), scaled down for samples closer together, but never below
//! `1/n` for the n-th sample: the first samples form an exact least-squares fit instead of
//! one biased towards the first point, and a burst of fast queries refines the fit instead of
//! shortening its memory to 30 samples.
//!
//! Slow samples: a round trip much longer than the fastest one (more than
//! `SLOW_FACTOR`·rtt_min + `SLOW_SLACK_S`) means a stall somewhere between the write and the
//! read, and the read time is uncertain by that much. Such a sample is skipped, unless no
//! sample was used for `SLOW_WINDOW_S` (so a link whose round trips grew for good is still
//! followed). The fastest round trip is aged by 10 µs per hour so a one-off lucky sample does
//! not rule forever.
//!
//! Start-up: `get_uptime` (the link's first exchange after the dictionary download) gives the
//! 64-bit clock and a first estimate at the nominal frequency; the regression starts with the
//! first `get_clock` sample. The link keeps querying every 50 ms for a few seconds after the
//! eight initial queries (see `LinkTuning::fast_clock_duration`): with samples that close, a
//! 20 µs read-time error is a 400 ppm slope error for a pair, so the slope needs many of them.
//!
//! Outliers: the regression predicts `ĉ` at `t`; the squared error is tracked as an EWMA
//! prediction variance. A sample whose error² exceeds 25× that variance (and 0.5 ms worth of
//! ticks) is dropped if it is *late* (`c > ĉ`: the query was delayed) and a good prediction was
//! made in the last 10 s; otherwise the variance is reset to the floor and the sample is used,
//! so a real change (a new frequency) is followed instead of rejected forever.
//!
//! 32→64-bit: a reported clock is widened around the *predicted* clock at the sample's time, not
//! the last reported value, so it stays right when the 32-bit counter wraps between queries
//! (every ~1.7 s for a simulator running 50× faster than real time). The prediction must be
//! within ±2^31 ticks, which holds once one sample has fixed the frequency.

mod seqlock;

pub use seqlock::SeqLock;

use rt_core::{McuClock, WireClock};

/// Regression decay per regular sample ([`DECAY_PERIOD_S`] apart).
pub const DECAY: f64 = 1.0 / 30.0;
/// The regular query period the decay is given for; closer samples decay less.
pub const DECAY_PERIOD_S: f64 = 0.98;
/// Ageing of the fastest half round trip, seconds per second.
pub const RTT_AGE: f64 = 10e-6 / 3600.0;
/// A sample is an outlier when its error² exceeds this many prediction variances.
pub const OUTLIER_FACTOR: f64 = 25.0;
/// Errors smaller than this (in seconds of MCU time) are never outliers.
pub const OUTLIER_FLOOR_S: f64 = 500e-6;
/// Late samples are rejected only while the last good prediction is younger than this.
pub const OUTLIER_WINDOW_S: f64 = 10.0;
/// A round trip longer than `SLOW_FACTOR`·fastest + `SLOW_SLACK_S` marks a slow sample.
pub const SLOW_FACTOR: f64 = 2.0;
/// See [`SLOW_FACTOR`].
pub const SLOW_SLACK_S: f64 = 250e-6;
/// A slow sample is used anyway when no sample was used for this long.
pub const SLOW_WINDOW_S: f64 = 2.5;
/// Prediction variance at start-up: 1 ms of MCU time, squared.
const INITIAL_STDDEV_S: f64 = 1e-3;

/// A snapshot of the clock mapping: cheap to copy, valid until the next sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockEstimate {
    ref_time: f64,
    ref_clock: f64,
    freq: f64,
    residual_us: f64,
}

impl Default for ClockEstimate {
    fn default() -> Self {
        ClockEstimate::INVALID
    }
}

impl ClockEstimate {
    /// No estimate yet: [`Self::is_valid`] is false and the clock reads 0.
    pub const INVALID: ClockEstimate = ClockEstimate {
        ref_time: 0.0,
        ref_clock: 0.0,
        freq: 0.0,
        residual_us: 0.0,
    };

    /// The mapping `clock(t) = ref_clock + (t − ref_time)·freq`.
    pub fn new(ref_time: f64, ref_clock: f64, freq: f64) -> ClockEstimate {
        ClockEstimate {
            ref_time,
            ref_clock,
            freq,
            residual_us: 0.0,
        }
    }

    /// True once a frequency is known.
    pub fn is_valid(&self) -> bool {
        self.freq.is_finite() && self.freq > 0.0
    }

    /// The estimated MCU clock at system time `system_time_s` (0 while invalid).
    pub fn clock_at(&self, system_time_s: f64) -> f64 {
        if !self.is_valid() {
            return 0.0;
        }
        self.ref_clock + (system_time_s - self.ref_time) * self.freq
    }

    /// The system time at which the MCU clock reaches `clock` (`ref_time` while invalid).
    pub fn system_time_at(&self, clock: f64) -> f64 {
        if !self.is_valid() {
            return self.ref_time;
        }
        self.ref_time + (clock - self.ref_clock) / self.freq
    }

    /// Ticks per system second (differs from `CLOCK_FREQ` under a simulator time scale).
    pub fn freq(&self) -> f64 {
        self.freq
    }

    /// Fit residual: the regression's predicted standard deviation, in µs of MCU time.
    pub fn residual_us(&self) -> f64 {
        self.residual_us
    }

    /// Widens a 32-bit clock from the wire around the predicted clock at `now_system`.
    pub fn extend(&self, wire: u32, now_system: f64) -> u64 {
        let predicted = self.clock_at(now_system).max(0.0) as u64;
        McuClock(predicted).extend(WireClock(wire)).0
    }

    fn to_words(self) -> [u64; 4] {
        [
            self.ref_time.to_bits(),
            self.ref_clock.to_bits(),
            self.freq.to_bits(),
            self.residual_us.to_bits(),
        ]
    }

    fn from_words(w: [u64; 4]) -> ClockEstimate {
        ClockEstimate {
            ref_time: f64::from_bits(w[0]),
            ref_clock: f64::from_bits(w[1]),
            freq: f64::from_bits(w[2]),
            residual_us: f64::from_bits(w[3]),
        }
    }
}

/// The latest [`ClockEstimate`], shared lock-free between the IO thread (writer) and any
/// number of readers (planner, step compressor).
#[derive(Debug)]
pub struct ClockShared(SeqLock<4>);

impl Default for ClockShared {
    fn default() -> Self {
        ClockShared::new(ClockEstimate::INVALID)
    }
}

impl ClockShared {
    /// Shared state holding `est`.
    pub fn new(est: ClockEstimate) -> ClockShared {
        ClockShared(SeqLock::new(est.to_words()))
    }

    /// Publishes a new estimate.
    pub fn store(&self, est: ClockEstimate) {
        self.0.store(est.to_words());
    }

    /// The latest estimate.
    pub fn load(&self) -> ClockEstimate {
        ClockEstimate::from_words(self.0.load())
    }
}

/// What became of one `clock` sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sample {
    /// Used in the regression.
    Accepted,
    /// Used after resetting the prediction variance (a large but plausible change).
    Reset,
    /// Dropped as a delayed reply.
    Outlier,
    /// Dropped for its long round trip (its read time is uncertain).
    Slow,
}

/// The regression state of one MCU's clock.
#[derive(Debug, Clone)]
pub struct ClockSync {
    nominal_freq: f64,
    time_avg: f64,
    /// Midpoint time of the last sample used.
    time_last: f64,
    clock_avg: f64,
    time_variance: f64,
    clock_covariance: f64,
    prediction_variance: f64,
    last_prediction_time: f64,
    min_half_rtt: f64,
    min_rtt_time: f64,
    last_clock: u64,
    last_used_time: f64,
    samples: u64,
    outliers: u64,
    slow: u64,
    last_error_us: f64,
    est: ClockEstimate,
}

impl ClockSync {
    /// A sync for an MCU whose dictionary states `nominal_freq` (CLOCK_FREQ).
    pub fn new(nominal_freq: f64) -> ClockSync {
        ClockSync {
            nominal_freq,
            time_avg: 0.0,
            time_last: 0.0,
            clock_avg: 0.0,
            time_variance: 0.0,
            clock_covariance: 0.0,
            prediction_variance: 0.0,
            last_prediction_time: 0.0,
            min_half_rtt: f64::INFINITY,
            min_rtt_time: 0.0,
            last_clock: 0,
            last_used_time: 0.0,
            samples: 0,
            outliers: 0,
            slow: 0,
            last_error_us: 0.0,
            est: ClockEstimate::INVALID,
        }
    }

    /// Starts from a `get_uptime` answer: the full 64-bit `clock`, queried at `sent_time` and
    /// answered at `receive_time` (system seconds). The first estimate uses the nominal
    /// frequency; the regression starts with the first `get_clock` sample.
    pub fn start(&mut self, clock: u64, sent_time: f64, receive_time: f64) {
        let half_rtt = (0.5 * (receive_time - sent_time)).max(0.0);
        let mid = sent_time + half_rtt;
        self.time_avg = mid;
        self.clock_avg = clock as f64;
        self.time_variance = 0.0;
        self.clock_covariance = 0.0;
        self.prediction_variance = (INITIAL_STDDEV_S * self.nominal_freq).powi(2);
        self.last_prediction_time = sent_time;
        self.min_half_rtt = half_rtt;
        self.min_rtt_time = sent_time;
        self.last_clock = clock;
        self.last_used_time = sent_time;
        self.samples = 0;
        self.est = ClockEstimate {
            ref_time: mid,
            ref_clock: clock as f64,
            freq: self.nominal_freq,
            residual_us: INITIAL_STDDEV_S * 1e6,
        };
    }

    /// Feeds one `clock` answer (32-bit `wire` clock) to a query written at `sent_time` and
    /// answered at `receive_time`.
    pub fn handle_clock(&mut self, wire: u32, sent_time: f64, receive_time: f64) -> Sample {
        let mid = 0.5 * (sent_time + receive_time);
        let clock_u64 = if self.est.is_valid() {
            self.est.extend(wire, mid)
        } else {
            McuClock(self.last_clock).extend(WireClock(wire)).0
        };
        self.last_clock = clock_u64;
        let clock = clock_u64 as f64;

        let half_rtt = (0.5 * (receive_time - sent_time)).max(0.0);
        let aged = (sent_time - self.min_rtt_time).max(0.0) * RTT_AGE;
        if half_rtt < self.min_half_rtt + aged {
            self.min_half_rtt = half_rtt;
            self.min_rtt_time = sent_time;
        }
        let min_rtt = 2.0 * (self.min_half_rtt + aged);
        if 2.0 * half_rtt > SLOW_FACTOR * min_rtt + SLOW_SLACK_S
            && sent_time < self.last_used_time + SLOW_WINDOW_S
        {
            self.slow += 1;
            return Sample::Slow;
        }

        let freq_now = if self.est.is_valid() {
            self.est.freq
        } else {
            self.nominal_freq
        };
        let gap = (mid - self.time_last).max(0.0);
        let alpha = (DECAY * (gap / DECAY_PERIOD_S).min(1.0)).max(1.0 / (self.samples + 1) as f64);
        let mut verdict = Sample::Accepted;
        if self.time_variance > 0.0 {
            let predicted =
                self.clock_avg + (mid - self.time_avg) * self.clock_covariance / self.time_variance;
            let err = clock - predicted;
            let err2 = err * err;
            self.last_error_us = err / freq_now * 1e6;
            let floor = (OUTLIER_FLOOR_S * freq_now).powi(2);
            if err2 > OUTLIER_FACTOR * self.prediction_variance && err2 > floor {
                if err > 0.0 && sent_time < self.last_prediction_time + OUTLIER_WINDOW_S {
                    self.outliers += 1;
                    return Sample::Outlier;
                }
                self.prediction_variance = floor;
                verdict = Sample::Reset;
            } else {
                self.last_prediction_time = sent_time;
                self.prediction_variance = (1.0 - alpha) * (self.prediction_variance + err2 * alpha);
            }
        }
        self.last_used_time = sent_time;

        if self.samples == 0 {
            // The regression's first point (the uptime answer only seeded the estimate).
            self.time_avg = mid;
            self.clock_avg = clock;
            self.time_last = mid;
            self.samples = 1;
            self.est.ref_time = mid;
            self.est.ref_clock = clock;
            return verdict;
        }
        let dt = mid - self.time_avg;
        self.time_avg += alpha * dt;
        self.time_variance = (1.0 - alpha) * (self.time_variance + dt * dt * alpha);
        let dc = clock - self.clock_avg;
        self.clock_avg += alpha * dc;
        self.clock_covariance = (1.0 - alpha) * (self.clock_covariance + dt * dc * alpha);
        self.time_last = mid;
        self.samples += 1;

        let freq = self.clock_covariance / self.time_variance;
        if freq.is_finite() && freq > 0.0 {
            self.est = ClockEstimate {
                ref_time: self.time_avg,
                ref_clock: self.clock_avg,
                freq,
                residual_us: self.prediction_variance.sqrt() / freq * 1e6,
            };
        }
        verdict
    }

    /// The current estimate.
    pub fn estimate(&self) -> ClockEstimate {
        self.est
    }

    /// The last reported clock, widened to 64 bits.
    pub fn last_clock(&self) -> u64 {
        self.last_clock
    }

    /// Samples used so far.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Samples dropped as outliers.
    pub fn outliers(&self) -> u64 {
        self.outliers
    }

    /// Samples skipped for a slow round trip.
    pub fn slow(&self) -> u64 {
        self.slow
    }

    /// Error of the last sample against the prediction, µs of MCU time.
    pub fn last_error_us(&self) -> f64 {
        self.last_error_us
    }

    /// Fastest half round trip seen (aged), seconds.
    pub fn min_half_rtt(&self) -> f64 {
        self.min_half_rtt
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::XorShift64;

    /// A simulated MCU clock: `clock(t) = c0 + ∫ freq`, with `freq` drifting linearly.
    struct TrueClock {
        c0: f64,
        f0: f64,
        drift_per_s: f64,
    }

    impl TrueClock {
        fn at(&self, t: f64) -> f64 {
            self.c0 + self.f0 * t + 0.5 * self.drift_per_s * t * t
        }
        fn freq(&self, t: f64) -> f64 {
            self.f0 + self.drift_per_s * t
        }
    }

    /// Runs start + 8 queries 50 ms apart + `n` queries 0.98 s apart; replies take 0.1..0.3 ms
    /// with the MCU reading its clock somewhere inside the round trip. Every `outlier_every`-th
    /// query is delayed by 20 ms before the MCU reads its clock.
    fn run(truth: &TrueClock, nominal: f64, n: usize, outlier_every: usize, seed: u64) -> (ClockSync, f64) {
        let mut rng = XorShift64::new(seed);
        let mut sync = ClockSync::new(nominal);
        let t0 = 1000.0;
        let sample = |t: f64, rng: &mut XorShift64, delay: f64| {
            let rtt = 100e-6 + 200e-6 * rng.next_f64();
            let read_at = t + delay + rtt * (0.3 + 0.4 * rng.next_f64());
            (truth.at(read_at - t0), t + delay + rtt)
        };
        let (c, recv) = sample(t0, &mut rng, 0.0);
        sync.start(c as u64, t0, recv);
        let mut t = t0;
        for i in 0..8 + n {
            t += if i < 8 { 0.05 } else { 0.98 };
            let late = outlier_every > 0 && i > 20 && i % outlier_every == 0;
            let (c, recv) = sample(t, &mut rng, if late { 20e-3 } else { 0.0 });
            let v = sync.handle_clock(c as u64 as u32, t, recv);
            if late {
                assert!(
                    matches!(v, Sample::Outlier | Sample::Slow),
                    "delayed sample {i} used"
                );
            } else {
                assert!(
                    matches!(v, Sample::Accepted | Sample::Reset),
                    "good sample {i}: {v:?}"
                );
                assert_eq!(sync.last_clock(), c as u64, "bad 64-bit extension at sample {i}");
            }
        }
        (sync, t - t0)
    }

    #[test]
    fn converges_on_a_noisy_50mhz_clock() {
        let truth = TrueClock {
            c0: 123_456_789.0,
            f0: 50_000_122.0,
            drift_per_s: 0.0,
        };
        let (sync, elapsed) = run(&truth, 50e6, 200, 0, 1);
        let est = sync.estimate();
        assert!((est.freq() / truth.f0 - 1.0).abs() < 5e-6, "freq {}", est.freq());
        let now = 1000.0 + elapsed;
        let err_s = (est.clock_at(now) - truth.at(elapsed)) / truth.f0;
        assert!(err_s.abs() < 100e-6, "clock error {err_s} s");
        assert!(est.residual_us() > 0.0 && est.residual_us() < 200.0);
        let back = est.system_time_at(est.clock_at(now));
        assert!((back - now).abs() < 1e-9);
    }

    #[test]
    fn initial_fit_is_good_even_when_nominal_freq_is_wrong() {
        // A simulator at 50× time scale: 2.5 GHz of ticks per system second; nominal 50 MHz.
        let truth = TrueClock {
            c0: 7.0e9,
            f0: 2.5e9,
            drift_per_s: 0.0,
        };
        let (sync, _) = run(&truth, 50e6, 0, 0, 2);
        let f = sync.estimate().freq();
        assert!((f / truth.f0 - 1.0).abs() < 0.01, "freq after 8 samples {f}");
    }

    #[test]
    fn follows_drift_and_wraps_under_time_scale() {
        // 2.5 GHz wraps the 32-bit clock every 1.7 s, more often than one query per 0.98 s
        // would notice from the last value alone; frequency drifts by 50 ppm over the run.
        let truth = TrueClock {
            c0: 5.0 * 4_294_967_296.0 + 17.0,
            f0: 2.5e9,
            drift_per_s: 2.5e9 * 50e-6 / 300.0,
        };
        let (sync, elapsed) = run(&truth, 50e6, 300, 0, 3);
        let est = sync.estimate();
        let rel = est.freq() / truth.freq(elapsed) - 1.0;
        assert!(rel.abs() < 20e-6, "freq error {rel}");
        // Extending a wire clock from any time in the next second lands on the true clock.
        let now = 1000.0 + elapsed;
        for k in 0..20 {
            let t = now + k as f64 * 0.05;
            let true_clock = truth.at(t - 1000.0) as u64;
            assert_eq!(est.extend(true_clock as u32, t), true_clock);
        }
    }

    #[test]
    fn delayed_replies_are_rejected() {
        let truth = TrueClock {
            c0: 0.0,
            f0: 50e6,
            drift_per_s: 0.0,
        };
        let (sync, _) = run(&truth, 50e6, 100, 7, 4);
        assert!(
            sync.slow() >= 10,
            "slow {} outliers {}",
            sync.slow(),
            sync.outliers()
        );
        assert!((sync.estimate().freq() / 50e6 - 1.0).abs() < 5e-6);
    }

    /// Start-up as the link does it (uptime, 8 queries 50 ms apart, then 50 ms apart for
    /// `fast_s`), with round trips of 100..300 µs where the MCU reads its clock anywhere
    /// between 30 % and 70 % of the trip, and a 2 ms stall before the read of the third query.
    /// Returns the estimate's error 0.5 s after the last sample, µs.
    fn startup_error_us(truth: &TrueClock, fast_s: f64, seed: u64) -> f64 {
        let mut rng = XorShift64::new(seed);
        let mut sync = ClockSync::new(50e6);
        let t0 = 1000.0;
        let mut sample = |t: f64, stall: f64| {
            let rtt = 100e-6 + 200e-6 * rng.next_f64();
            let read_at = t + stall + rtt * (0.3 + 0.4 * rng.next_f64());
            (truth.at(read_at - t0), t + stall + rtt)
        };
        let (c, recv) = sample(t0, 0.0);
        sync.start(c as u64, t0, recv);
        let mut t = t0;
        let n = 8 + (fast_s / 0.05) as usize;
        for i in 0..n {
            t += 0.05;
            let (c, recv) = sample(t, if i == 2 { 2e-3 } else { 0.0 });
            sync.handle_clock(c as u64 as u32, t, recv);
        }
        let at = t + 0.5;
        (sync.estimate().clock_at(at) - truth.at(at - t0)) / truth.f0 * 1e6
    }

    #[test]
    fn the_estimate_is_good_soon_after_start_despite_a_stall() {
        let truth = TrueClock {
            c0: 123_456_789.0,
            f0: 50_000_122.0,
            drift_per_s: 0.0,
        };
        // Right when the link becomes ready (8 samples), then after 1 s and 3 s of fast
        // queries. Moves on two MCUs are planned through two such estimates, so errors add.
        let fast = [0.0, 1.0, 3.0];
        let mut worst = [0.0f64; 3];
        for seed in 1..=20 {
            for (w, fast_s) in worst.iter_mut().zip(fast) {
                *w = w.max(startup_error_us(&truth, fast_s, seed).abs());
            }
        }
        for (w, limit) in worst.iter().zip([120.0, 50.0, 30.0]) {
            assert!(
                *w < limit,
                "worst errors {worst:?} us after {fast:?} s of fast queries"
            );
        }
        assert!(worst[2] < worst[0] / 2.0, "fast queries did not help: {worst:?}");
    }

    #[test]
    fn a_real_frequency_change_is_followed() {
        let mut sync = ClockSync::new(50e6);
        sync.start(0, 0.0, 0.0001);
        let mut t = 0.0;
        let mut clock = 0.0;
        let mut freq = 50e6;
        for i in 0..400 {
            t += 0.98;
            if i == 100 {
                freq = 50.5e6; // +1 %: every sample now looks late at first
            }
            clock += 0.98 * freq;
            sync.handle_clock(clock as u64 as u32, t, t + 0.0001);
        }
        let f = sync.estimate().freq();
        assert!(
            (f / 50.5e6 - 1.0).abs() < 1e-4,
            "freq {f} outliers {}",
            sync.outliers()
        );
        assert!(sync.outliers() <= 12);
    }

    #[test]
    fn estimate_helpers() {
        let inv = ClockEstimate::INVALID;
        assert!(!inv.is_valid());
        assert_eq!(inv.clock_at(5.0), 0.0);
        let est = ClockEstimate::new(10.0, 1000.0, 100.0);
        assert_eq!(est.clock_at(11.0), 1100.0);
        assert_eq!(est.system_time_at(1200.0), 12.0);
        // Across a wrap: predicted just below 2^32, wire just above.
        let est = ClockEstimate::new(0.0, 4_294_967_000.0, 1000.0);
        assert_eq!(est.extend(100, 0.0), 4_294_967_396);
        let shared = ClockShared::default();
        assert!(!shared.load().is_valid());
        shared.store(est);
        assert_eq!(shared.load(), est);
    }
}

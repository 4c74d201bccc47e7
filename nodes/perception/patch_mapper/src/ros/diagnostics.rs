//! `/diagnostics` (`diagnostic_msgs/DiagnosticArray`, 1 Hz) of patch_mapper, hardware id
//! `patch_mapper`: input rates (depth, IMU, camera info), processing latency (depth received →
//! patches published, p50/p99 over the last second), frames dropped and why, whether frames are
//! being mapped and how tracking fares (tracking), and the map size. Levels: OK, WARN (an input
//! missing or no frame mapped while frames arrive, frames dropped, tracking lost: relocalising or
//! the map reset), ERROR (no depth frames at all).
//!
//! `tracking` tells the two kinds of loss apart: a short loss ("lost, relocalising against the map",
//! WARN while it lasts; "lost → relocalised after N frames", OK, once it ended, the map kept) and a
//! real loss ("tracking lost: map reset", WARN), with their totals as values.
//!
//! The numbers come from the node's `MapperStatus` counters, sampled by the loop on every pass. The
//! latency is the one of the latest mapped frame at each pass: when two frames finish between two
//! passes only the later one is sampled.
//!
//! With the foothold stage on (`ros.footholds.enabled`), `footholds` reports its prediction rate,
//! the frames it dropped for newer ones (network busy or rate limit), the last prediction's time and
//! footholds, and the last route: OK, WARN when frames are offered but none was predicted, or the
//! last prediction failed.

use std::time::Instant;

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::diagnostic_msgs::msg::{DiagnosticArray, DiagnosticStatus, KeyValue};
use patchwalk_msgs::msg::MapperStatus;

use patchwalk_ros::diagnostics::kv;

use super::footholds::FootholdHealth;
pub use patchwalk_ros::diagnostics::{DIAGNOSTICS_PERIOD, DIAGNOSTICS_TOPIC};
pub const HARDWARE_ID: &str = "patch_mapper";
/// The timing entry that holds the end-to-end latency (`MapperStatus.timing_names`).
pub(super) const LATENCY_NAME: &str = "depth_in_to_patches_out";

const OK: u8 = DiagnosticStatus::OK;
const WARN: u8 = DiagnosticStatus::WARN;
const ERROR: u8 = DiagnosticStatus::ERROR;

/// How tracking fares, kept by the pipeline thread (`MapperStatus` has no fields for it).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrackingHealth {
    /// Frames lost in a row right now (0: tracking).
    pub frames_lost: u64,
    /// `tracker.relocalisation.max_lost_frames`.
    pub max_lost_frames: u64,
    /// Short losses ended by relocalising against the kept map.
    pub relocalisations: u64,
    /// Frames lost in the last short loss that ended.
    pub last_relocalised_after: u64,
    /// Real losses: the map was reset.
    pub map_resets: u64,
    /// Why the last frame without a pose failed.
    pub last_loss: String,
}

/// Counters at the start of the window and the latencies sampled in it.
#[derive(Debug, Default)]
pub struct MapperWindow {
    start: Option<(Instant, MapperStatus)>,
    start_tracking: TrackingHealth,
    last_processed: u64,
    latencies_ms: Vec<f64>,
}

impl MapperWindow {
    /// Sample the status (every loop pass): the latency of a newly mapped frame.
    pub fn sample(&mut self, status: &MapperStatus, now: Instant) {
        if self.start.is_none() {
            self.start = Some((now, status.clone()));
            self.last_processed = status.frames_processed;
        }
        if status.frames_processed > self.last_processed {
            self.last_processed = status.frames_processed;
            let latency = status.timing_names.iter().position(|n| n == LATENCY_NAME).and_then(|i| status.timing_ms.get(i));
            if let Some(ms) = latency {
                self.latencies_ms.push(*ms);
            }
        }
    }

    /// The array for the window ending at `now` (then a new window starts).
    pub fn diagnostics(&mut self, status: &MapperStatus, tracking: &TrackingHealth, now: Instant, stamp: Time) -> DiagnosticArray {
        let (since, before) = self.start.take().unwrap_or_else(|| (now, status.clone()));
        let seconds = now.duration_since(since).as_secs_f64();
        let rate = |after: u64, before: u64| if seconds > 0.0 { after.saturating_sub(before) as f64 / seconds } else { 0.0 };
        let rates = Rates {
            depth_hz: rate(status.frames_received, before.frames_received),
            imu_hz: rate(status.imu_received, before.imu_received),
            camera_info_hz: rate(status.camera_infos_received, before.camera_infos_received),
            processed_hz: rate(status.frames_processed, before.frames_processed),
            skipped: status.frames_skipped.saturating_sub(before.frames_skipped),
            rejected: status.frames_rejected.saturating_sub(before.frames_rejected),
        };
        let mut latencies = std::mem::take(&mut self.latencies_ms);
        latencies.sort_by(f64::total_cmp);
        let statuses = vec![
            inputs_status(&rates),
            latency_status(&latencies),
            dropped_status(status, &rates),
            tracking_status(status, &rates, tracking, &self.start_tracking),
            map_status(status),
        ];
        self.start = Some((now, status.clone()));
        self.start_tracking = tracking.clone();
        patchwalk_ros::diagnostics::array(stamp, statuses)
    }
}

struct Rates {
    depth_hz: f64,
    imu_hz: f64,
    camera_info_hz: f64,
    processed_hz: f64,
    skipped: u64,
    rejected: u64,
}

fn status(level: u8, name: &str, message: impl Into<String>, values: Vec<KeyValue>) -> DiagnosticStatus {
    patchwalk_ros::diagnostics::status(HARDWARE_ID, level, name, message, values)
}

/// The `q` quantile (0..1) of sorted values, nearest rank.
pub(crate) fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted.get(rank.min(last)).copied()
}

fn inputs_status(r: &Rates) -> DiagnosticStatus {
    let values = vec![
        kv("depth_hz", format!("{:.1}", r.depth_hz)),
        kv("imu_hz", format!("{:.1}", r.imu_hz)),
        kv("camera_info_hz", format!("{:.1}", r.camera_info_hz)),
    ];
    let missing: Vec<&str> = [("depth", r.depth_hz), ("IMU", r.imu_hz), ("camera info", r.camera_info_hz)]
        .iter()
        .filter(|(_, hz)| *hz <= 0.0)
        .map(|(name, _)| *name)
        .collect();
    if r.depth_hz <= 0.0 {
        return status(ERROR, "inputs", format!("no depth frames in the last second (also missing: {})", missing.join(", ")), values);
    }
    if !missing.is_empty() {
        return status(WARN, "inputs", format!("no {} in the last second", missing.join(", ")), values);
    }
    status(OK, "inputs", format!("depth {:.0} Hz, IMU {:.0} Hz, camera info {:.0} Hz", r.depth_hz, r.imu_hz, r.camera_info_hz), values)
}

fn latency_status(sorted: &[f64]) -> DiagnosticStatus {
    let (Some(p50), Some(p99)) = (quantile(sorted, 0.5), quantile(sorted, 0.99)) else {
        return status(OK, "latency", "no frame mapped in the last second", vec![kv("samples", 0)]);
    };
    let values = vec![kv("p50_ms", format!("{p50:.1}")), kv("p99_ms", format!("{p99:.1}")), kv("samples", sorted.len())];
    status(OK, "latency", format!("depth to patches p50 {p50:.1} ms, p99 {p99:.1} ms"), values)
}

fn dropped_status(s: &MapperStatus, r: &Rates) -> DiagnosticStatus {
    let values = vec![
        kv("skipped_last_second", r.skipped),
        kv("rejected_last_second", r.rejected),
        kv("skipped_total", s.frames_skipped),
        kv("rejected_total", s.frames_rejected),
        kv("last_error", &s.last_error),
    ];
    if r.skipped + r.rejected == 0 {
        return status(OK, "dropped frames", "none in the last second", values);
    }
    let why = if s.last_error.is_empty() { "the pipeline was busy".to_string() } else { s.last_error.clone() };
    status(WARN, "dropped frames", format!("{} skipped, {} rejected in the last second; last: {why}", r.skipped, r.rejected), values)
}

fn tracking_status(s: &MapperStatus, r: &Rates, t: &TrackingHealth, before: &TrackingHealth) -> DiagnosticStatus {
    let values = vec![
        kv("mapped_hz", format!("{:.1}", r.processed_hz)),
        kv("frames_processed", s.frames_processed),
        kv("frames_lost", t.frames_lost),
        kv("relocalisations_total", t.relocalisations),
        kv("map_resets_total", t.map_resets),
        kv("last_loss", &t.last_loss),
    ];
    if t.frames_lost > 0 {
        let message =
            format!("lost, relocalising against the map ({} of at most {} frames): {}", t.frames_lost, t.max_lost_frames, t.last_loss);
        return status(WARN, "tracking", message, values);
    }
    let resets = t.map_resets.saturating_sub(before.map_resets);
    if resets > 0 {
        return status(WARN, "tracking", format!("tracking lost: map reset ({resets} in the last second): {}", t.last_loss), values);
    }
    let relocalised = t.relocalisations.saturating_sub(before.relocalisations);
    if relocalised > 0 {
        let message = format!(
            "mapping {:.0} frames/s; lost → relocalised after {} frames, map kept ({relocalised} in the last second; last loss: {})",
            r.processed_hz, t.last_relocalised_after, t.last_loss
        );
        return status(OK, "tracking", message, values);
    }
    if r.depth_hz > 0.0 && r.processed_hz <= 0.0 {
        let why = if s.last_error.is_empty() { "no reason reported".to_string() } else { s.last_error.clone() };
        return status(WARN, "tracking", format!("depth frames arrive but none was mapped: {why}"), values);
    }
    if r.processed_hz <= 0.0 {
        return status(OK, "tracking", "idle (no depth frames)", values);
    }
    status(OK, "tracking", format!("mapping {:.0} frames/s", r.processed_hz), values)
}

/// The foothold stage's counters at the start of the window.
#[derive(Debug, Default)]
pub struct FootholdWindow {
    start: Option<(Instant, FootholdHealth)>,
}

impl FootholdWindow {
    /// The `footholds` status for the window ending at `now` (then a new window starts).
    pub fn status(&mut self, health: &FootholdHealth, now: Instant) -> DiagnosticStatus {
        let (since, before) = self.start.take().unwrap_or_else(|| (now, health.clone()));
        self.start = Some((now, health.clone()));
        let seconds = now.duration_since(since).as_secs_f64();
        let predicted = health.predicted.saturating_sub(before.predicted);
        let offered = health.offered.saturating_sub(before.offered);
        let dropped = health.dropped.saturating_sub(before.dropped);
        let hz = if seconds > 0.0 { predicted as f64 / seconds } else { 0.0 };
        let limit = if health.max_rate_hz > 0.0 { format!("limit {:.1} Hz", health.max_rate_hz) } else { "no rate limit".to_string() };
        let values = vec![
            kv("predicted_hz", format!("{hz:.2}")),
            kv("offered_last_window", offered),
            kv("dropped_last_window", dropped),
            kv("predicted_total", health.predicted),
            kv("dropped_total", health.dropped),
            kv("last_regions_ms", format!("{:.1}", health.last_regions_ms)),
            kv("last_network_ms", format!("{:.1}", health.last_network_ms)),
            kv("last_footholds", health.last_holds),
            kv("routes_total", health.routes),
            kv("last_route", &health.last_route),
            kv("last_error", &health.last_error),
        ];
        if !health.last_error.is_empty() {
            return status(WARN, "footholds", format!("last prediction failed: {}", health.last_error), values);
        }
        if offered > 0 && predicted == 0 && health.predicted == 0 {
            return status(WARN, "footholds", format!("{offered} frames offered, none predicted yet"), values);
        }
        let message = format!(
            "predicting {hz:.1} frames/s ({limit}), {dropped} of {offered} frames dropped for newer ones; last: {} footholds, network {:.0} ms",
            health.last_holds, health.last_network_ms
        );
        status(OK, "footholds", message, values)
    }
}

fn map_status(s: &MapperStatus) -> DiagnosticStatus {
    status(OK, "map", format!("{} patches", s.patches_in_map), vec![kv("patches", s.patches_in_map)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn find<'a>(array: &'a DiagnosticArray, name: &str) -> &'a DiagnosticStatus {
        array.status.iter().find(|s| s.name == format!("{HARDWARE_ID}: {name}")).unwrap()
    }

    #[test]
    fn rates_latency_quantiles_and_drops_over_one_window() {
        let t0 = Instant::now();
        let mut window = MapperWindow::default();
        let mut s = MapperStatus { timing_names: vec![LATENCY_NAME.into()], ..Default::default() };
        window.sample(&s, t0);
        for i in 1..=30u64 {
            s.frames_received = i;
            s.frames_processed = i;
            s.imu_received = 10 * i;
            s.camera_infos_received = i;
            s.timing_ms = vec![i as f64];
            window.sample(&s, t0 + Duration::from_millis(33 * i));
        }
        s.frames_skipped = 2;
        s.last_error = "depth frame skipped: no CameraInfo yet".into();
        let array = window.diagnostics(&s, &TrackingHealth::default(), t0 + Duration::from_secs(1), Time::default());
        assert_eq!(find(&array, "inputs").level, OK);
        let latency = find(&array, "latency");
        assert!(latency.message.contains("p50 15.0 ms") && latency.message.contains("p99 30.0 ms"), "{}", latency.message);
        let dropped = find(&array, "dropped frames");
        assert_eq!(dropped.level, WARN);
        assert!(dropped.message.contains("2 skipped") && dropped.message.contains("CameraInfo"), "{}", dropped.message);
        assert!(array.status.iter().all(|st| st.hardware_id == HARDWARE_ID));
    }

    #[test]
    fn frames_arriving_but_none_mapped_warn_and_no_depth_is_an_error() {
        let t0 = Instant::now();
        let mut window = MapperWindow::default();
        let mut s = MapperStatus::default();
        window.sample(&s, t0);
        s.frames_received = 30;
        s.last_error = "ICP did not converge".into();
        let array = window.diagnostics(&s, &TrackingHealth::default(), t0 + Duration::from_secs(1), Time::default());
        let tracking = find(&array, "tracking");
        assert_eq!(tracking.level, WARN);
        assert!(tracking.message.contains("ICP"), "{}", tracking.message);
        assert_eq!(find(&array, "inputs").level, WARN, "IMU and camera info missing");
        let array = window.diagnostics(&s, &TrackingHealth::default(), t0 + Duration::from_secs(2), Time::default());
        assert_eq!(find(&array, "inputs").level, ERROR);
    }

    #[test]
    fn short_losses_and_map_resets_are_reported_apart() {
        let t0 = Instant::now();
        let mut window = MapperWindow::default();
        let mut s = MapperStatus { frames_received: 30, frames_processed: 30, ..Default::default() };
        window.sample(&s, t0);
        let mut health = TrackingHealth { max_lost_frames: 10, ..TrackingHealth::default() };
        let second = |k: u64| t0 + Duration::from_secs(k);
        // Tracking as usual.
        let tracking = |array: &DiagnosticArray| find(array, "tracking").clone();
        s.frames_received += 30;
        s.frames_processed += 30;
        let ok = tracking(&window.diagnostics(&s, &health, second(1), Time::default()));
        assert_eq!(ok.level, OK);
        assert!(ok.message.starts_with("mapping"), "{}", ok.message);
        // A short loss in progress: WARN, relocalising, the map kept.
        health.frames_lost = 2;
        health.last_loss = "too few ICP inliers (12 of 900 associated)".into();
        s.frames_received += 30;
        s.frames_processed += 28;
        let lost = tracking(&window.diagnostics(&s, &health, second(2), Time::default()));
        assert_eq!(lost.level, WARN);
        assert!(lost.message.contains("relocalising against the map (2 of at most 10 frames)"), "{}", lost.message);
        // It ended: OK, "lost → relocalised".
        health.frames_lost = 0;
        health.relocalisations = 1;
        health.last_relocalised_after = 2;
        s.frames_received += 30;
        s.frames_processed += 30;
        let back = tracking(&window.diagnostics(&s, &health, second(3), Time::default()));
        assert_eq!(back.level, OK);
        assert!(back.message.contains("lost → relocalised after 2 frames, map kept"), "{}", back.message);
        // The next second without events is plain again.
        s.frames_received += 30;
        s.frames_processed += 30;
        assert!(tracking(&window.diagnostics(&s, &health, second(4), Time::default())).message.starts_with("mapping"));
        // A real loss: WARN, the map reset, named apart from the short losses.
        health.map_resets = 1;
        health.last_loss = "ICP residual 25.0 mm RMS".into();
        s.frames_received += 30;
        s.frames_processed += 30;
        let reset = tracking(&window.diagnostics(&s, &health, second(5), Time::default()));
        assert_eq!(reset.level, WARN);
        assert!(reset.message.starts_with("tracking lost: map reset (1 in the last second)"), "{}", reset.message);
        let value = |key: &str| reset.values.iter().find(|v| v.key == key).map(|v| v.value.clone());
        assert_eq!((value("relocalisations_total"), value("map_resets_total")), (Some("1".into()), Some("1".into())));
    }

    #[test]
    fn the_foothold_stage_reports_its_rate_drops_and_failures() {
        let t0 = Instant::now();
        let mut window = FootholdWindow::default();
        let mut health = FootholdHealth { max_rate_hz: 2.0, ..Default::default() };
        window.status(&health, t0);
        // Offered at 30 Hz, none predicted yet (the network is still on its first frame).
        health.offered = 30;
        health.dropped = 29;
        let waiting = window.status(&health, t0 + Duration::from_secs(1));
        assert_eq!(waiting.level, WARN);
        assert!(waiting.message.contains("none predicted yet"), "{}", waiting.message);
        health.offered = 60;
        health.dropped = 57;
        health.predicted = 2;
        health.last_holds = 12;
        health.last_network_ms = 480.0;
        let ok = window.status(&health, t0 + Duration::from_secs(2));
        assert_eq!(ok.level, OK);
        assert!(ok.message.contains("predicting 2.0 frames/s (limit 2.0 Hz), 28 of 30 frames dropped"), "{}", ok.message);
        assert!(ok.message.contains("12 footholds"), "{}", ok.message);
        health.last_error = "camera tilt: gravity is zero or not finite".into();
        let failed = window.status(&health, t0 + Duration::from_secs(3));
        assert_eq!(failed.level, WARN);
        assert!(failed.message.contains("camera tilt"), "{}", failed.message);
        assert_eq!(failed.name, format!("{HARDWARE_ID}: footholds"));
    }

    #[test]
    fn quantiles_use_the_nearest_rank() {
        assert_eq!(quantile(&[], 0.5), None);
        assert_eq!(quantile(&[4.0], 0.99), Some(4.0));
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(quantile(&v, 0.5), Some(50.0));
        assert_eq!(quantile(&v, 0.99), Some(99.0));
    }
}

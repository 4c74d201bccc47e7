//! Pairing each depth image with its CameraInfo: the one of the same stamp (drivers publish both per
//! frame), else the latest one of the image's size (a driver that publishes CameraInfo less often, or
//! one that does not stamp it like its images). An image whose size no recent CameraInfo has (the
//! stamp-matched one included) is rejected, naming both sizes.

use std::collections::VecDeque;

use patchwalk_fusion::camera::Intrinsics;
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_ros::clock::stamp_ns;

/// How many recent CameraInfos are kept (at 30 Hz, half a second).
const KEPT: usize = 16;

/// Why a depth image has no intrinsics.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PairingError {
    #[error("no valid CameraInfo received yet")]
    NoCameraInfo,
    #[error("depth image is {width}x{height} but its CameraInfo (same stamp) says {info_width}x{info_height}")]
    StampedSizeMismatch { width: usize, height: usize, info_width: usize, info_height: usize },
    #[error("depth image is {width}x{height} but the latest CameraInfo says {info_width}x{info_height} (no recent one of that size)")]
    SizeMismatch { width: usize, height: usize, info_width: usize, info_height: usize },
}

/// The recent CameraInfos, newest last.
#[derive(Debug, Default)]
pub struct CameraInfoPairing {
    recent: VecDeque<(i64, Intrinsics)>,
}

impl CameraInfoPairing {
    pub fn push(&mut self, stamp: &Time, intrinsics: Intrinsics) {
        if self.recent.len() == KEPT {
            self.recent.pop_front();
        }
        self.recent.push_back((stamp_ns(stamp), intrinsics));
    }

    /// The intrinsics for an image of `width`×`height` stamped `stamp`.
    pub fn pair(&self, stamp: &Time, width: usize, height: usize) -> Result<Intrinsics, PairingError> {
        let stamp = stamp_ns(stamp);
        let Some((_, latest)) = self.recent.back() else {
            return Err(PairingError::NoCameraInfo);
        };
        let fits = |k: &Intrinsics| (k.width, k.height) == (width, height);
        if stamp != 0 {
            if let Some((_, same_stamp)) = self.recent.iter().rev().find(|(s, _)| *s == stamp) {
                return if fits(same_stamp) {
                    Ok(*same_stamp)
                } else {
                    Err(PairingError::StampedSizeMismatch { width, height, info_width: same_stamp.width, info_height: same_stamp.height })
                };
            }
        }
        self.recent.iter().rev().map(|(_, k)| *k).find(fits).ok_or(PairingError::SizeMismatch {
            width,
            height,
            info_width: latest.width,
            info_height: latest.height,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k(width: usize, fx: f64) -> Intrinsics {
        Intrinsics::new(width, width * 3 / 4, fx, fx, width as f64 / 2.0, width as f64 * 3.0 / 8.0).unwrap()
    }

    fn t(sec: i32) -> Time {
        Time { sec, nanosec: 0 }
    }

    #[test]
    fn images_get_the_camera_info_of_their_stamp_else_the_latest_of_their_size() {
        let mut pairing = CameraInfoPairing::default();
        assert_eq!(pairing.pair(&t(1), 640, 480), Err(PairingError::NoCameraInfo));
        pairing.push(&t(1), k(640, 570.0));
        pairing.push(&t(2), k(640, 575.0));
        pairing.push(&t(3), k(320, 285.0));
        assert_eq!(pairing.pair(&t(1), 640, 480).unwrap().fx, 570.0, "same stamp");
        assert_eq!(pairing.pair(&t(9), 640, 480).unwrap().fx, 575.0, "latest of the size");
        assert_eq!(pairing.pair(&t(0), 320, 240).unwrap().fx, 285.0, "unstamped");
        let error = pairing.pair(&t(3), 640, 480).unwrap_err();
        assert_eq!(error, PairingError::StampedSizeMismatch { width: 640, height: 480, info_width: 320, info_height: 240 });
        let error = pairing.pair(&t(4), 800, 600).unwrap_err().to_string();
        assert!(error.contains("800x600") && error.contains("320x240"), "{error}");
    }

    #[test]
    fn only_recent_camera_infos_are_kept() {
        let mut pairing = CameraInfoPairing::default();
        pairing.push(&t(0), k(320, 285.0));
        for i in 1..=KEPT as i32 {
            pairing.push(&t(i), k(640, 570.0));
        }
        assert!(matches!(pairing.pair(&t(100), 320, 240), Err(PairingError::SizeMismatch { .. })));
    }
}

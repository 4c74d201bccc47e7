//! What a failed frame does to the tracker: the relocalisation state machine.
//!
//! J 5.2 resets the whole patch map when camera tracking fails. A walking robot loses single frames
//! (a foot strike jolts the camera, a frame comes in empty or late), and the map it has built is still
//! right. So a failed frame only starts a *short loss*: the volume, the model raycast and the last good
//! pose are kept, the frame is not fused, and the next frames are aligned against the kept model from
//! the constant-velocity prediction and from the last good pose, with the wide ICP level. The first
//! frame that passes the loss checks ends the loss (relocalised); only `max_lost_frames` failed
//! frames in a row are a real loss, which resets the volume as J 5.2 does.
//!
//! ```text
//!            ok                         failed (k + 1 ≤ N)
//!  Tracking ────► Tracking     Lost(k) ───────────────────► Lost(k + 1)      (coasting: map kept)
//!     │ failed (N ≥ 1)            │ ok
//!     ▼                           ▼                           failed (k + 1 > N)
//!  Lost(1)                     Tracking (relocalised after k)  Lost(k) ─────────────► Tracking (reset)
//! ```

/// Where the tracker is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum RecoveryState {
    #[default]
    Tracking,
    /// The last `frames` frames failed; the map and the last good pose are kept.
    Lost { frames: usize },
}

/// What a frame's outcome means.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transition {
    /// Tracked as usual.
    Tracked,
    /// Tracked again after `frames_lost` failed frames, against the kept map.
    Relocalised { frames_lost: usize },
    /// This frame failed too; `frames_lost` in a row so far (at most `max_lost_frames`).
    Coasting { frames_lost: usize },
    /// More than `max_lost_frames` failed in a row (or short losses are off): reset the map.
    Reset,
}

/// The state machine of short losses.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Recovery {
    state: RecoveryState,
    max_lost_frames: usize,
}

impl Recovery {
    /// `max_lost_frames` = 0: every failure is a reset (J 5.2 as written).
    pub fn new(max_lost_frames: usize) -> Self {
        Self { state: RecoveryState::Tracking, max_lost_frames }
    }

    pub fn state(&self) -> RecoveryState {
        self.state
    }

    /// Frames lost in a row so far (0 while tracking).
    pub fn frames_lost(&self) -> usize {
        match self.state {
            RecoveryState::Tracking => 0,
            RecoveryState::Lost { frames } => frames,
        }
    }

    /// A frame passed the loss checks.
    pub fn on_tracked(&mut self) -> Transition {
        let transition = match self.state {
            RecoveryState::Tracking => Transition::Tracked,
            RecoveryState::Lost { frames } => Transition::Relocalised { frames_lost: frames },
        };
        self.state = RecoveryState::Tracking;
        transition
    }

    /// A frame failed every attempt.
    pub fn on_failed(&mut self) -> Transition {
        let frames = self.frames_lost() + 1;
        if frames > self.max_lost_frames {
            self.state = RecoveryState::Tracking;
            return Transition::Reset;
        }
        self.state = RecoveryState::Lost { frames };
        Transition::Coasting { frames_lost: frames }
    }

    /// Back to tracking (the map was reset or re-initialised).
    pub fn reset(&mut self) {
        self.state = RecoveryState::Tracking;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_losses_coast_then_relocalise_and_long_ones_reset() {
        let mut recovery = Recovery::new(3);
        assert_eq!(recovery.on_tracked(), Transition::Tracked);
        assert_eq!(recovery.on_failed(), Transition::Coasting { frames_lost: 1 });
        assert_eq!(recovery.state(), RecoveryState::Lost { frames: 1 });
        assert_eq!(recovery.on_failed(), Transition::Coasting { frames_lost: 2 });
        assert_eq!(recovery.on_tracked(), Transition::Relocalised { frames_lost: 2 });
        assert_eq!((recovery.state(), recovery.frames_lost()), (RecoveryState::Tracking, 0));
        // Three failures coast, the fourth resets and tracking starts over.
        for k in 1..=3 {
            assert_eq!(recovery.on_failed(), Transition::Coasting { frames_lost: k });
        }
        assert_eq!(recovery.on_failed(), Transition::Reset);
        assert_eq!(recovery.state(), RecoveryState::Tracking);
        assert_eq!(recovery.on_tracked(), Transition::Tracked);
        // An explicit reset while lost.
        recovery.on_failed();
        recovery.reset();
        assert_eq!(recovery.on_tracked(), Transition::Tracked);
    }

    #[test]
    fn no_short_losses_means_every_failure_resets() {
        let mut recovery = Recovery::new(0);
        assert_eq!(recovery.on_failed(), Transition::Reset);
        assert_eq!(recovery.on_failed(), Transition::Reset);
        assert_eq!(recovery.frames_lost(), 0);
    }
}

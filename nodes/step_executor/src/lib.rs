//! step_executor: ROS-free execution library of patchwalk.
//!
//! A trained library of (patch relative to the robot -> keyframe motion), a matcher with the
//! thresholds of J 6.3, a keyframe player, and the servo bus (Dynamixel Protocol 2.0) with real,
//! simulated (pty) and mock implementations.

pub mod config;
pub mod kinematics;
pub mod library;
pub mod matcher;
pub mod mx28;
pub mod patch;
pub mod player;
pub mod servo_bus;
pub mod protocol;
pub mod sim_chain;
pub mod executor;
pub mod runtime;

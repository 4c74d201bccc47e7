//! step_executor: ROS-free execution library of patchwalk.
//!
//! A trained library of (patch relative to the robot -> keyframe motion), a matcher with the
//! thresholds of J 6.3, a keyframe player on the servo bus thread, and the node's logic without
//! ROS ([`runtime`]), and ROBOTIS action files read and written as library motions ([`action_file`]).
//! The servos are reached through `patchwalk_dynamixel`, the robot through
//! `patchwalk_robot_model`. [`inputs`] takes what the node receives as bytes (serialized requests and
//! patch maps, the library and configuration files) through the same checks, for the fuzz targets.

pub mod action_file;
pub mod config;
pub mod cycle_clock;
pub mod executor;
pub mod health;
pub mod inputs;
pub mod library;
pub mod matcher;
pub mod player;
pub mod runtime;
pub mod slow_bus;

//! Rust side of the `patchwalk_msgs` ROS 2 interface package.
//!
//! The `.msg`/`.srv` files next to this crate are the single source of truth; the Rust structs here
//! mirror them field by field (the CDR wire format is positional).

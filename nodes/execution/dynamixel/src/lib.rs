//! Dynamixel Protocol 2.0 for the MX-28 servos of patchwalk: the MX-28 control table, packet
//! encoding and parsing (CRC-16), the [`servo_bus::ServoBus`] seam with the real RS-485 master
//! (dynamixel2, with its known defects worked around), a mock, and a byte-level simulated servo chain
//! on a pty ([`sim_chain`]) for tests. ROS-free.

pub mod mx28;
pub mod priority;
pub mod protocol;
pub mod servo_bus;
pub mod sim_chain;

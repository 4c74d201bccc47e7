//! terrain_sim: ROS-free rough-terrain simulator library of patchwalk.

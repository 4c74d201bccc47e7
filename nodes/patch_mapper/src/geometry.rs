//! Pose geometry of IROS II: exponential/log maps, their Jacobians, 5-DoF rotations, pose chains and covariance propagation.

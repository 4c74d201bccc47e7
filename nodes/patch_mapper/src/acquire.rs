//! Stage i (J 4.1): depth image + intrinsics -> organized cloud in the camera frame; IMU -> gravity in the camera frame.

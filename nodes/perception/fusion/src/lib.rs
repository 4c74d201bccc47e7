//! Depth fusion and camera tracking of patchwalk's perception (J 5): the pinhole camera model and
//! depth images, datasets on disk (TUM RGB-D layout, PNG depth), the TSDF volume of voxel blocks
//! with projective integration, raycasting, point-to-plane ICP against the raycast, the moving
//! volume that follows the camera, IMU gravity calibration, and trajectory metrics.
//!
//! ROS-free; used by the mapping library and the simulator.

pub mod calibration;
pub mod camera;
pub mod dataset;
pub mod fusion;
pub mod raycast;
pub mod tracking;
pub mod trajectory;
pub mod volume;

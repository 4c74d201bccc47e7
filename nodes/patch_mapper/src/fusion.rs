//! TSDF volume (J 5): voxel-block layout, projective integration of depth frames.

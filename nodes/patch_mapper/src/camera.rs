//! Pinhole camera intrinsics and depth images (metres, NaN where invalid); back-projection to organized clouds.

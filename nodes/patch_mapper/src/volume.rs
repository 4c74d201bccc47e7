//! Moving-volume policy (J 4, 5.1-5.2): gravity-aligned volume frame, remaps when the camera leaves its nominal pose.

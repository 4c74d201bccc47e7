//! IMU-camera rotation calibration (J 2.2) by orthogonal Procrustes on plane normals and gravity.

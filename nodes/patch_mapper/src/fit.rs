//! Patch fitting (IROS IV steps 1-9): LLS plane, weighted Levenberg-Marquardt, type discrimination, boundary moments, output covariance.

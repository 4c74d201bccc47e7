//! Range-sensor point covariances: Murray-Little pointing/disparity model (J eq 2) and constant/linear/quadratic range models.

//! Point files for the CLI: CSV (x,y,z[,covariance]) and PLY.

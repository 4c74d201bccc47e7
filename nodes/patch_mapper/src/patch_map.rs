//! The patch map kept around the robot: ids, grid cells, first/last seen.

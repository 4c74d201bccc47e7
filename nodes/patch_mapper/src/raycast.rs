//! Raycasting the TSDF from the real camera (for ICP) and from the birds-eye virtual camera (for the mapper).

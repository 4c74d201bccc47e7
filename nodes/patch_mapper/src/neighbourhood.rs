//! Stage iv (J 4.4): r-ball neighbourhoods by image back-projection, nf uniformly spread points.

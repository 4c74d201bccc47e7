//! The homogeneous patch map (J 4.6) kept around the robot: patches with ids, their grid cell on the
//! volume's horizontal xz-plane (J 4.3), first/last seen times; rigid moves, box culling and cell
//! re-association for patch tracking (J 5.2 step 6).
//!
//! Frames: patches are stored in the map's named frame `frame_id` (normally `map`, gravity aligned,
//! z up). The grid lives in the `volume` frame (J 4: corner origin, y along gravity, x and z along the
//! cube edges); [`VolumeGrid::volume_from_map`] ties the two. When the volume is remapped, either call
//! [`PatchMap::set_grid`] with the new `volume_from_map` (patches stay put in the map frame), or, if
//! patches are kept in the volume frame itself, [`PatchMap::transform_all`] with the remap.

use nalgebra::{Isometry3, Vector3};

use patchwalk_spl::patch::Patch;
use patchwalk_spl::transform::transform_patch;

/// A cell of the Vg × Vg grid on the volume xz-plane: `(ix, iz)`.
pub type Cell = (usize, usize);

/// The Vg × Vg grid on the horizontal xz-plane of a cubic volume of edge Vs (J 4.3 step 7).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeGrid {
    /// Pose of the map frame in the volume frame.
    pub volume_from_map: Isometry3<f64>,
    /// Vs: edge of the cubic volume (m).
    pub edge_m: f64,
    /// Vg: cells per side.
    pub cells_per_side: usize,
}

impl VolumeGrid {
    /// Side of one cell (m).
    pub fn cell_size_m(&self) -> f64 {
        self.edge_m / self.cells_per_side.max(1) as f64
    }

    /// Whether a point in the volume frame lies inside the cube `[0, Vs]³`.
    pub fn contains_in_volume(&self, point_in_volume: &Vector3<f64>) -> bool {
        point_in_volume.iter().all(|&c| (0.0..=self.edge_m).contains(&c))
    }

    /// J step 8: the cell of a point given in the volume frame (its xz projection); `None` outside.
    pub fn cell_of_volume_point(&self, point_in_volume: &Vector3<f64>) -> Option<Cell> {
        let size = self.cell_size_m();
        let (x, z) = (point_in_volume.x / size, point_in_volume.z / size);
        let n = self.cells_per_side as f64;
        if !(x >= 0.0 && z >= 0.0 && x < n && z < n) {
            return None;
        }
        Some((x as usize, z as usize))
    }

    /// The cell of a point in the map frame.
    pub fn cell_of_map_point(&self, point_in_map: &Vector3<f64>) -> Option<Cell> {
        self.cell_of_volume_point(&(self.volume_from_map * nalgebra::Point3::from(*point_in_map)).coords)
    }

    /// Flat index of a cell (`iz · Vg + ix`).
    pub fn flat(&self, cell: Cell) -> usize {
        cell.1 * self.cells_per_side + cell.0
    }

    /// Centre `(x, z)` of a cell in the volume frame.
    pub fn cell_centre_xz(&self, cell: Cell) -> (f64, f64) {
        let size = self.cell_size_m();
        ((cell.0 as f64 + 0.5) * size, (cell.1 as f64 + 0.5) * size)
    }

    /// J step 9: all cells ordered by increasing distance of their centre to `(x, z)` (the camera
    /// projected on the xz-plane); ties keep row-major order.
    pub fn cells_by_distance(&self, x: f64, z: f64) -> Vec<Cell> {
        let n = self.cells_per_side;
        let mut cells: Vec<(f64, Cell)> = (0..n)
            .flat_map(|iz| (0..n).map(move |ix| (ix, iz)))
            .map(|cell| {
                let (cx, cz) = self.cell_centre_xz(cell);
                ((cx - x).powi(2) + (cz - z).powi(2), cell)
            })
            .collect();
        cells.sort_by(|a, b| a.0.total_cmp(&b.0));
        cells.into_iter().map(|(_, cell)| cell).collect()
    }
}

/// A patch in the map.
#[derive(Debug, Clone, PartialEq)]
pub struct MappedPatch {
    /// Unique id within the map (never reused).
    pub id: u64,
    /// The patch, its pose in the map's frame.
    pub patch: Patch,
    /// Grid cell of the patch centre (J 4.3), `None` if outside the grid.
    pub cell: Option<Cell>,
    /// Timestamp (s) of the frame the patch was fitted in.
    pub first_seen: f64,
    /// Timestamp (s) of the last frame that fitted or tracked it.
    pub last_seen: f64,
    /// Observations fused into the patch since it was added or changed type (1 for a new patch).
    pub observations: u32,
    /// The map's frame counter ([`PatchMap::set_frame`]) at the last observation.
    pub observed_frame: u64,
    /// The point (map frame) whose r-ball neighbourhood defines the patch: the seed it was fitted
    /// to (J step 10), or its centre when it was added without one. Re-observations fit the same ball.
    pub anchor: Vector3<f64>,
}

/// The patch map: patches in frame `frame_id`, gridded by a [`VolumeGrid`].
#[derive(Debug, Clone, PartialEq)]
pub struct PatchMap {
    /// Name of the frame the patch poses are in (e.g. `map`).
    pub frame_id: String,
    grid: VolumeGrid,
    patches: Vec<MappedPatch>,
    next_id: u64,
    frame: u64,
}

impl PatchMap {
    /// An empty map.
    pub fn new(frame_id: impl Into<String>, grid: VolumeGrid) -> Self {
        Self { frame_id: frame_id.into(), grid, patches: Vec::new(), next_id: 0, frame: 0 }
    }

    /// The grid.
    pub fn grid(&self) -> &VolumeGrid {
        &self.grid
    }

    /// All patches, in insertion order.
    pub fn patches(&self) -> &[MappedPatch] {
        &self.patches
    }

    /// Number of patches.
    pub fn len(&self) -> usize {
        self.patches.len()
    }

    /// Whether the map holds no patch.
    pub fn is_empty(&self) -> bool {
        self.patches.is_empty()
    }

    /// Adds a patch (pose in `frame_id`) seen at `timestamp`, in the cell of its centre; returns its id.
    pub fn insert(&mut self, patch: Patch, timestamp: f64) -> u64 {
        let cell = self.grid.cell_of_map_point(&patch.center);
        self.insert_in_cell(patch, cell, timestamp)
    }

    /// Adds a patch associated with `cell` (J 4.3: the cell of the seed it was fitted to; the
    /// fitted centre can lie just across a cell border). Returns its id.
    pub fn insert_in_cell(&mut self, patch: Patch, cell: Option<Cell>, timestamp: f64) -> u64 {
        let anchor = patch.center;
        self.insert_anchored(patch, cell, anchor, timestamp)
    }

    /// Adds a patch fitted to the r-ball around `anchor` (map frame; the seed point), in `cell`.
    /// Returns its id.
    pub fn insert_anchored(&mut self, patch: Patch, cell: Option<Cell>, anchor: Vector3<f64>, timestamp: f64) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.patches.push(MappedPatch {
            id,
            patch,
            cell,
            first_seen: timestamp,
            last_seen: timestamp,
            observations: 1,
            observed_frame: self.frame,
            anchor,
        });
        id
    }

    /// Sets the frame counter recorded with each observation (the mapper's frame number), which
    /// tells re-observation how many frames apart two observations of a patch are.
    pub fn set_frame(&mut self, frame: u64) {
        self.frame = frame;
    }

    /// The frame counter of [`PatchMap::set_frame`].
    pub fn frame(&self) -> u64 {
        self.frame
    }

    /// The patch with id `id`.
    pub fn get(&self, id: u64) -> Option<&MappedPatch> {
        self.patches.iter().find(|p| p.id == id)
    }

    /// Mutable access to the patch with id `id` (for the fusion of re-observations).
    pub(crate) fn get_mut(&mut self, id: u64) -> Option<&mut MappedPatch> {
        self.patches.iter_mut().find(|p| p.id == id)
    }

    /// Removes the patch with id `id`; returns it.
    pub fn remove(&mut self, id: u64) -> Option<MappedPatch> {
        let index = self.patches.iter().position(|p| p.id == id)?;
        Some(self.patches.remove(index))
    }

    /// Marks a patch as seen at `timestamp`; false if the id is unknown.
    pub fn touch(&mut self, id: u64, timestamp: f64) -> bool {
        match self.patches.iter_mut().find(|p| p.id == id) {
            Some(p) => {
                p.last_seen = timestamp;
                true
            }
            None => false,
        }
    }

    /// Patches per cell, flat-indexed (J 4.3: "ignore new seeds for a cell that already has at
    /// least ng patches").
    pub fn cell_counts(&self) -> Vec<usize> {
        let mut counts = vec![0; self.grid.cells_per_side * self.grid.cells_per_side];
        for cell in self.patches.iter().filter_map(|p| p.cell) {
            if let Some(c) = counts.get_mut(self.grid.flat(cell)) {
                *c += 1;
            }
        }
        counts
    }

    /// J 5.2 step 6 (first bullet): moves every patch by `new_from_old` (with first-order covariance
    /// propagation) and renames the frame; cells are re-associated.
    pub fn transform_all(&mut self, new_from_old: &Isometry3<f64>, new_frame_id: impl Into<String>) {
        self.frame_id = new_frame_id.into();
        for mapped in &mut self.patches {
            if let Some(moved) = transform_patch(&mapped.patch, new_from_old) {
                mapped.patch = moved;
            }
            mapped.anchor = (new_from_old * nalgebra::Point3::from(mapped.anchor)).coords;
        }
        self.reassociate();
    }

    /// J 5.2 step 6 (third bullet): a new grid (e.g. after a volume remap); cells re-associated.
    pub fn set_grid(&mut self, grid: VolumeGrid) {
        self.grid = grid;
        self.reassociate();
    }

    /// J 5.2 step 6 (second bullet): drops the patches whose centre left the volume cube; returns
    /// how many were dropped.
    pub fn drop_outside_volume(&mut self) -> usize {
        let grid = self.grid;
        self.retain(|p| grid.contains_in_volume(&(grid.volume_from_map * nalgebra::Point3::from(p.patch.center)).coords))
    }

    /// Keeps the patches for which `keep` holds (e.g. "not farther than dcp behind the camera");
    /// returns how many were dropped.
    pub fn retain(&mut self, keep: impl FnMut(&MappedPatch) -> bool) -> usize {
        let before = self.patches.len();
        self.patches.retain(keep);
        before - self.patches.len()
    }

    /// J 4.3: culls the extra patches of cells holding more than `max_per_cell`, keeping the most
    /// recently seen ones; returns how many were dropped.
    pub fn cull_crowded_cells(&mut self, max_per_cell: usize) -> usize {
        let mut order: Vec<usize> = (0..self.patches.len()).collect();
        order.sort_by(|&a, &b| self.patches[b].last_seen.total_cmp(&self.patches[a].last_seen));
        let mut counts = vec![0usize; self.grid.cells_per_side * self.grid.cells_per_side];
        let mut keep = vec![true; self.patches.len()];
        for index in order {
            if let Some(cell) = self.patches[index].cell {
                let flat = self.grid.flat(cell);
                if let Some(count) = counts.get_mut(flat) {
                    *count += 1;
                    keep[index] = *count <= max_per_cell;
                }
            }
        }
        let mut flags = keep.into_iter();
        self.retain(|_| flags.next().unwrap_or(true))
    }

    /// Keeps the `max` most recently seen patches (the newer id first among equals) and drops the
    /// rest; returns how many were dropped.
    pub fn keep_most_recent(&mut self, max: usize) -> usize {
        if self.patches.len() <= max {
            return 0;
        }
        let mut order: Vec<(f64, u64, usize)> = self.patches.iter().enumerate().map(|(i, p)| (p.last_seen, p.id, i)).collect();
        order.sort_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
        let mut keep = vec![false; self.patches.len()];
        for &(_, _, index) in order.iter().take(max) {
            if let Some(flag) = keep.get_mut(index) {
                *flag = true;
            }
        }
        let mut flags = keep.into_iter();
        self.retain(|_| flags.next().unwrap_or(true))
    }

    /// Summary statistics of the map.
    pub fn stats(&self) -> MapStats {
        let n = self.patches.len();
        let occupied = self.cell_counts().iter().filter(|&&c| c > 0).count();
        MapStats {
            patches: n,
            occupied_cells: occupied,
            mean_residual_m: if n == 0 { 0.0 } else { self.patches.iter().map(|p| p.patch.residual).sum::<f64>() / n as f64 },
            total_area_m2: self.patches.iter().map(|p| p.patch.boundary_area()).sum(),
        }
    }

    fn reassociate(&mut self) {
        for mapped in &mut self.patches {
            mapped.cell = self.grid.cell_of_map_point(&mapped.patch.center);
        }
    }
}

/// Statistics of a patch map.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MapStats {
    pub patches: usize,
    pub occupied_cells: usize,
    pub mean_residual_m: f64,
    pub total_area_m2: f64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector2};
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};

    fn grid() -> VolumeGrid {
        VolumeGrid { volume_from_map: Isometry3::identity(), edge_m: 1.6, cells_per_side: 8 }
    }

    fn plane_at(center: Vector3<f64>) -> Patch {
        Patch::new(SurfaceType::Plane, BoundaryType::Ellipse, vec![0.05, 0.03], Vector2::zeros(), Vector3::new(0.1, -0.2, 0.3), center)
            .unwrap()
    }

    #[test]
    fn cells_are_found_and_ordered_by_distance() {
        let g = grid();
        assert_eq!(g.cell_of_volume_point(&Vector3::new(0.05, 9.0, 0.25)), Some((0, 1)));
        assert_eq!(g.cell_of_volume_point(&Vector3::new(1.6, 0.0, 0.0)), None);
        assert_eq!(g.cell_of_volume_point(&Vector3::new(-0.01, 0.0, 0.0)), None);
        let order = g.cells_by_distance(0.8, 0.0);
        assert_eq!(order.len(), 64);
        // Nearest cells to the middle of the back edge: (3, 0) and (4, 0).
        assert!(order[..2].contains(&(3, 0)) && order[..2].contains(&(4, 0)));
        let distances: Vec<f64> = order
            .iter()
            .map(|&c| {
                let (x, z) = g.cell_centre_xz(c);
                (x - 0.8).hypot(z)
            })
            .collect();
        assert!(distances.windows(2).all(|w| w[0] <= w[1] + 1e-12));
    }

    #[test]
    fn insert_count_cull_and_drop() {
        let mut map = PatchMap::new("map", grid());
        let a = map.insert(plane_at(Vector3::new(0.1, 0.5, 0.1)), 1.0);
        let b = map.insert(plane_at(Vector3::new(0.12, 0.5, 0.1)), 2.0);
        map.insert(plane_at(Vector3::new(1.0, 0.5, 1.0)), 2.0);
        assert_ne!(a, b);
        let counts = map.cell_counts();
        assert_eq!(counts[0], 2);
        assert_eq!(counts.iter().sum::<usize>(), 3);
        assert!(map.touch(a, 5.0));
        assert!(!map.touch(99, 5.0));
        // Cull to one per cell keeps the most recently seen (a).
        assert_eq!(map.cull_crowded_cells(1), 1);
        assert!(map.patches().iter().any(|p| p.id == a) && !map.patches().iter().any(|p| p.id == b));
        // Shift the grid 0.5 m along x: the patch at x = 0.1 leaves the cube.
        let mut shifted = grid();
        shifted.volume_from_map = Isometry3::translation(-0.5, 0.0, 0.0);
        map.set_grid(shifted);
        assert_eq!(map.drop_outside_volume(), 1);
        assert_eq!(map.len(), 1);
        assert_eq!(map.patches()[0].cell, Some((2, 5)));
        let stats = map.stats();
        assert_eq!((stats.patches, stats.occupied_cells), (1, 1));
        assert!((stats.total_area_m2 - std::f64::consts::PI * 0.05 * 0.03).abs() < 1e-9);
    }

    #[test]
    fn a_full_map_keeps_the_most_recently_seen_patches() {
        let mut map = PatchMap::new("map", grid());
        let ids: Vec<u64> = (0..6).map(|i| map.insert(plane_at(Vector3::new(0.1 + 0.2 * f64::from(i), 0.5, 0.1)), 1.0)).collect();
        assert!(map.touch(ids[0], 3.0));
        assert!(map.touch(ids[2], 2.0));
        assert_eq!(map.keep_most_recent(6), 0);
        // Kept: the two seen later, then the newest of those seen at 1.0.
        assert_eq!(map.keep_most_recent(3), 3);
        let mut kept: Vec<u64> = map.patches().iter().map(|p| p.id).collect();
        kept.sort_unstable();
        assert_eq!(kept, vec![ids[0], ids[2], ids[5]]);
        assert_eq!(map.keep_most_recent(0), 3);
        assert!(map.is_empty());
    }

    #[test]
    fn transform_all_moves_every_patch_and_renames_the_frame() {
        let patch = plane_at(Vector3::new(0.3, 0.2, 1.0));
        let t = Isometry3::from_parts(Translation3::new(0.5, -1.0, 2.0), UnitQuaternion::from_euler_angles(0.3, -0.5, 1.2));
        let moved = transform_patch(&patch, &t).unwrap();
        let mut map = PatchMap::new("volume", grid());
        map.insert(patch.clone(), 0.0);
        map.transform_all(&t, "map");
        assert_eq!(map.frame_id, "map");
        assert!((map.patches()[0].patch.center - moved.center).norm() < 1e-12);
        // The anchor (here the centre: no seed given) moves with the patch.
        assert!((map.patches()[0].anchor - moved.center).norm() < 1e-12);
        assert_eq!(map.patches()[0].observations, 1);
    }
}

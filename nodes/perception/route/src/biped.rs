//! The biped as the planner sees it (CNN IV's limb workspaces, made for the RPBP): two
//! [`LegModel`]s, the body's height and yaw workspace, the reach and the minimum foot separation,
//! all derived from the URDF.
//!
//! - **Reach** (CNN: "a sphere of radius 0.7 m centred at its shoulder"): here the sole can be at most
//!   thigh + shin (0.200 m, from the URDF) from the hip centre, plus the ankle-to-sole 0.035 m
//!   straight down (the sole is kept level). The planner uses it as a quick filter before the IK.
//! - **Minimum separation** (CNN: holds "< 0.3 m apart" are filtered out to avoid limb interference):
//!   the width of the foot's collision box (0.06 m in `urdf/rpbp.urdf`): two level soles whose centres
//!   are closer than a sole is wide overlap whatever their yaw.
//! - **Height workspace**: base_link above the stance's holds from the fully crouched height (knee at
//!   its upper limit, 2.4 rad: 0.060 + 0.0725 + 0.035 = 0.168 m) to the straight-leg height
//!   (0.060 + 0.200 + 0.035 = 0.295 m).
//! - **Yaw workspace**: the body turned relative to the feet within the hip-yaw limits (±1.2 rad).

use nalgebra::Vector3;
use patchwalk_robot_model::kinematics::RobotModel;

use crate::error::RouteError;
use crate::leg::{LegModel, Side};

/// The two legs and the workspace the planner samples.
#[derive(Debug, Clone, PartialEq)]
pub struct BipedModel {
    pub left: LegModel,
    pub right: LegModel,
    /// Lowest and highest base_link height above the stance's holds (m).
    pub height_range_m: (f64, f64),
    /// Body yaw relative to the feet's heading (rad): the hip-yaw range both legs allow.
    pub yaw_range_rad: (f64, f64),
    /// Two holds closer than this cannot both carry a foot (m): the sole's width.
    pub min_separation_m: f64,
    /// The sole's length (m): soles side by side closer than their width overlap unless one is at
    /// least this far ahead.
    pub sole_length_m: f64,
}

impl BipedModel {
    /// The RPBP shipped with patchwalk (`urdf/rpbp.urdf`).
    pub fn rpbp() -> Result<Self, RouteError> {
        Self::from_urdf_str(patchwalk_robot_model::RPBP_URDF)
    }

    /// Derives the model from URDF text (legs of the DARwIn-OP form, `l_`/`r_` joints, soles
    /// `left_foot`/`right_foot`, feet `l_foot_link`/`r_foot_link` with a box collision shape).
    pub fn from_urdf_str(text: &str) -> Result<Self, RouteError> {
        let model = RobotModel::from_urdf_str(text).map_err(|e| RouteError::Robot(e.to_string()))?;
        let left = LegModel::from_robot(&model, Side::Left)?;
        let right = LegModel::from_robot(&model, Side::Right)?;
        let robot = urdf_rs::read_from_string(text).map_err(|e| RouteError::Robot(e.to_string()))?;
        let mut width = f64::INFINITY;
        let mut length = f64::INFINITY;
        for name in ["l_foot_link", "r_foot_link"] {
            let link = robot.links.iter().find(|l| l.name == name).ok_or_else(|| RouteError::Robot(format!("no link {name}")))?;
            let size = link
                .collision
                .iter()
                .find_map(|c| match &c.geometry {
                    urdf_rs::Geometry::Box { size } => Some(size.0),
                    _ => None,
                })
                .ok_or_else(|| RouteError::Robot(format!("link {name} has no box collision shape (the sole)")))?;
            width = width.min(size[0].min(size[1]));
            length = length.min(size[0].max(size[1]));
        }
        let depth_below_base = |leg: &LegModel, length: f64| -leg.hip_in_base.z + length + leg.ankle_to_sole_m;
        let low = depth_below_base(&left, left.min_length_m()).max(depth_below_base(&right, right.min_length_m()));
        let high = depth_below_base(&left, left.length_m()).min(depth_below_base(&right, right.length_m()));
        let yaw = (left.limits[0].lower.max(right.limits[0].lower), left.limits[0].upper.min(right.limits[0].upper));
        if !(low < high && yaw.0 <= yaw.1 && width > 0.0) {
            return Err(RouteError::Robot(format!(
                "empty workspace: heights {low:.3}..{high:.3} m, hip yaw {:.2}..{:.2} rad",
                yaw.0, yaw.1
            )));
        }
        Ok(Self { left, right, height_range_m: (low, high), yaw_range_rad: yaw, min_separation_m: width, sole_length_m: length })
    }

    /// The leg of `side`.
    pub fn leg(&self, side: Side) -> &LegModel {
        match side {
            Side::Left => &self.left,
            Side::Right => &self.right,
        }
    }

    /// The farthest a sole can be from the body's vertical axis (m): hip offset + leg length.
    pub fn horizontal_reach_m(&self) -> f64 {
        let reach = |l: &LegModel| l.hip_in_base.xy().norm() + l.length_m();
        reach(&self.left).max(reach(&self.right))
    }

    /// Whether both soles are reachable (IK inside the joint limits) with base_link at `base` in the
    /// fixed frame, upright, yawed by `base_yaw`, and the feet yawed by `feet_yaw` (fixed frame); the
    /// legs must not cross (the left sole left of the right one in the feet's frame) and the soles
    /// must not overlap.
    pub fn stance_reachable(&self, base: &Vector3<f64>, base_yaw: f64, feet_yaw: f64, left: &Vector3<f64>, right: &Vector3<f64>) -> bool {
        let (fs, fc) = feet_yaw.sin_cos();
        let d = left - right;
        let (ahead, lateral) = (fc * d.x + fs * d.y, -fs * d.x + fc * d.y);
        if lateral < 0.0 || (lateral < self.min_separation_m && ahead.abs() < self.sole_length_m) {
            return false;
        }
        let (s, c) = base_yaw.sin_cos();
        let to_base = |p: &Vector3<f64>| {
            let d = p - base;
            Vector3::new(c * d.x + s * d.y, -s * d.x + c * d.y, d.z)
        };
        let relative_yaw = feet_yaw - base_yaw;
        self.left.ik(&to_base(left), relative_yaw).is_some() && self.right.ik(&to_base(right), relative_yaw).is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rpbp_workspace_is_derived_from_the_urdf() {
        let biped = BipedModel::rpbp().unwrap();
        let (low, high) = biped.height_range_m;
        assert!((high - 0.295).abs() < 1e-12, "{high}");
        assert!((low - (0.060 + 0.2 * (1.2f64).cos() + 0.035)).abs() < 1e-12, "{low}");
        assert_eq!(biped.yaw_range_rad, (-1.2, 1.2));
        assert!((biped.min_separation_m - 0.06).abs() < 1e-12);
        assert!((biped.sole_length_m - 0.10).abs() < 1e-12);
        assert!((biped.horizontal_reach_m() - 0.237).abs() < 1e-12);
    }

    /// Stances at known positions: feet under the hips at a crouch (feasible); feet swapped (left
    /// foot on the right: infeasible); a 0.45 m stride (beyond two legs' reach: infeasible).
    #[test]
    fn stance_feasibility_at_known_positions() {
        let biped = BipedModel::rpbp().unwrap();
        let base = Vector3::new(1.0, 2.0, 0.25);
        let left = Vector3::new(1.0, 2.037, 0.0);
        let right = Vector3::new(1.0, 1.963, 0.0);
        assert!(biped.stance_reachable(&base, 0.0, 0.0, &left, &right));
        // Staggered by 6 cm: reachable.
        assert!(biped.stance_reachable(&base, 0.0, 0.0, &Vector3::new(1.03, 2.037, 0.0), &Vector3::new(0.97, 1.963, 0.0)));
        // Swapped: the left foot 10 cm to the right of the right one (the legs would cross).
        assert!(!biped.stance_reachable(&base, 0.0, 0.0, &Vector3::new(1.0, 1.93, 0.0), &Vector3::new(1.0, 2.03, 0.0)));
        // Stride of 0.45 m along x: each foot 0.225 m from the hip horizontally at 0.19 m below it.
        assert!(!biped.stance_reachable(&base, 0.0, 0.0, &Vector3::new(1.225, 2.037, 0.0), &Vector3::new(0.775, 1.963, 0.0)));
        // Soles overlapping: 4 cm apart side by side.
        assert!(!biped.stance_reachable(&base, 0.0, 0.0, &Vector3::new(1.0, 2.02, 0.0), &Vector3::new(1.0, 1.98, 0.0)));
        // A short stride of 0.16 m: reachable.
        assert!(biped.stance_reachable(&base, 0.0, 0.0, &Vector3::new(1.08, 2.037, 0.0), &Vector3::new(0.92, 1.963, 0.0)));
        // Base too high (0.30 m above the holds, the straight leg is 0.295 m): unreachable.
        assert!(!biped.stance_reachable(&Vector3::new(1.0, 2.0, 0.30), 0.0, 0.0, &left, &right));
        // Rotated frame: base yawed 90° with the feet, holds along x.
        let yawed = std::f64::consts::FRAC_PI_2;
        assert!(biped.stance_reachable(&base, yawed, yawed, &Vector3::new(0.963, 2.0, 0.0), &Vector3::new(1.037, 2.0, 0.0)));
        assert!(!biped.stance_reachable(&base, yawed, yawed, &Vector3::new(1.037, 2.0, 0.0), &Vector3::new(0.963, 2.0, 0.0)));
    }

    #[test]
    fn a_urdf_without_feet_is_an_error() {
        assert!(matches!(BipedModel::from_urdf_str("<robot name=\"x\"><link name=\"a\"/></robot>"), Err(RouteError::Robot(_))));
    }
}

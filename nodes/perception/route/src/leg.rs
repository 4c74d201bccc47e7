//! One leg of the RPBP from its URDF, with a closed-form inverse kinematics for a level sole.
//!
//! The leg is DARwIn-OP-like (hip yaw about z, hip roll about x, hip pitch, knee and ankle pitch
//! about y, ankle roll about x): the three hip axes meet at the hip centre `c`, the two ankle axes at
//! the ankle centre `e`, thigh length a = |knee − c|, shin length b = |e − knee|, and the sole lies
//! s = |sole − e| below the ankle. All four numbers are read from the URDF by forward kinematics at
//! the zero pose ([`LegModel::from_robot`]), and the solver is checked against the URDF's forward
//! kinematics on load, so a model that is not of this form is refused instead of mis-solved.
//!
//! IK (sole at p in base_link, level, yawed by ψ_f): e = p + s·z; u = R_footᵀ (c − e);
//! knee k = acos((|u|² − a² − b²) / 2ab); ankle roll = atan2(u_y, u_z);
//! ankle pitch = atan2(−a sin k, a cos k + b) − atan2(u_x, √(u_y² + u_z²));
//! Rz(yaw)·Rx(roll)·Ry(pitch) = R_foot·Rx(−ankle roll)·Ry(−(k + ankle pitch)), read off its
//! third row and second column. A target is reachable when the solution exists and every joint is
//! inside its URDF limits.

use std::collections::HashMap;

use nalgebra::{Rotation3, Vector3};
use patchwalk_robot_model::kinematics::{JointLimits, RobotModel};

use crate::error::RouteError;

/// Left or right leg.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    Left,
    Right,
}

impl Side {
    /// The URDF joint-name prefix (`l` / `r`).
    pub fn prefix(self) -> &'static str {
        match self {
            Side::Left => "l",
            Side::Right => "r",
        }
    }

    /// The URDF sole frame (`left_foot` / `right_foot`).
    pub fn sole_link(self) -> &'static str {
        match self {
            Side::Left => "left_foot",
            Side::Right => "right_foot",
        }
    }
}

/// The six joints of a leg in chain order.
pub const LEG_JOINTS: [&str; 6] = ["hip_yaw", "hip_roll", "hip_pitch", "knee", "ankle_pitch", "ankle_roll"];

/// A leg's geometry and joint limits from the URDF.
#[derive(Debug, Clone, PartialEq)]
pub struct LegModel {
    pub side: Side,
    /// Hip centre c in base_link (m): where the hip axes meet.
    pub hip_in_base: Vector3<f64>,
    /// Thigh a: hip centre to knee (m).
    pub thigh_m: f64,
    /// Shin b: knee to ankle centre (m).
    pub shin_m: f64,
    /// Ankle centre to sole (m).
    pub ankle_to_sole_m: f64,
    /// Limits of the six joints in [`LEG_JOINTS`] order (rad).
    pub limits: [JointLimits; 6],
}

/// Joint tolerance on the limits (rad) and on the straight-leg length (m): numerical slack only.
const LIMIT_SLACK: f64 = 1e-9;

impl LegModel {
    /// Reads the leg from a URDF robot model (the RPBP's `urdf/rpbp.urdf` or one of the same form).
    pub fn from_robot(model: &RobotModel, side: Side) -> Result<Self, RouteError> {
        let p = side.prefix();
        let robot = |e: patchwalk_robot_model::kinematics::KinematicsError| RouteError::Robot(e.to_string());
        let zeros: HashMap<String, f64> = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect();
        let at = |link: &str| model.root_from_link(link, &zeros).map(|t| t.translation.vector).map_err(robot);
        let yaw_origin = at(&format!("{p}_hip_yaw_link"))?;
        let hip = at(&format!("{p}_hip_roll_link"))?;
        let pitch = at(&format!("{p}_thigh"))?;
        let knee = at(&format!("{p}_shin"))?;
        let ankle = at(&format!("{p}_ankle_link"))?;
        let roll = at(&format!("{p}_foot_link"))?;
        let sole = at(side.sole_link())?;
        let horizontal = |v: Vector3<f64>| v.xy().norm();
        let mismatch = [
            ("hip yaw axis and hip centre", horizontal(hip - yaw_origin)),
            ("hip roll and hip pitch", (pitch - hip).norm()),
            ("thigh (not straight down)", horizontal(knee - hip)),
            ("shin (not straight down)", horizontal(ankle - knee)),
            ("ankle pitch and roll", (roll - ankle).norm()),
            ("sole (not below the ankle)", horizontal(sole - ankle)),
        ];
        for (what, off) in mismatch {
            if off > 1e-9 {
                return Err(RouteError::Robot(format!("{p} leg is not of the DARwIn-OP form: {what} offset by {off:.4} m")));
            }
        }
        let mut limits = [JointLimits { lower: 0.0, upper: 0.0 }; 6];
        for (limit, joint) in limits.iter_mut().zip(LEG_JOINTS) {
            let name = format!("{p}_{joint}");
            *limit = model.joint_limits(&name).map_err(robot)?.ok_or_else(|| RouteError::Robot(format!("joint {name} has no limits")))?;
        }
        let leg = Self {
            side,
            hip_in_base: hip,
            thigh_m: (hip - knee).norm(),
            shin_m: (knee - ankle).norm(),
            ankle_to_sole_m: (ankle - sole).norm(),
            limits,
        };
        leg.check_against(model)?;
        Ok(leg)
    }

    /// Hip centre to ankle centre with the leg straight (m).
    pub fn length_m(&self) -> f64 {
        self.thigh_m + self.shin_m
    }

    /// Hip centre to ankle centre with the knee at its upper limit (m): the shortest the leg gets.
    pub fn min_length_m(&self) -> f64 {
        let (a, b) = (self.thigh_m, self.shin_m);
        let k = self.limits[3].upper.min(std::f64::consts::PI);
        (a * a + b * b + 2.0 * a * b * k.cos()).max(0.0).sqrt()
    }

    /// Joint angles ([`LEG_JOINTS`] order) placing the sole at `sole_in_base`, level, yawed by
    /// `foot_yaw` about base z; `None` when out of reach or outside a joint limit (checked joint by
    /// joint as the solution is built, ankle first, so most unreachable targets stop early).
    pub fn ik(&self, sole_in_base: &Vector3<f64>, foot_yaw: f64) -> Option<[f64; 6]> {
        self.solve(sole_in_base, foot_yaw, true)
    }

    fn solve(&self, sole_in_base: &Vector3<f64>, foot_yaw: f64, limited: bool) -> Option<[f64; 6]> {
        let inside =
            |joint: usize, q: f64| !limited || (q >= self.limits[joint].lower - LIMIT_SLACK && q <= self.limits[joint].upper + LIMIT_SLACK);
        let (a, b) = (self.thigh_m, self.shin_m);
        let (sy, cy) = foot_yaw.sin_cos();
        let d = self.hip_in_base - sole_in_base - Vector3::new(0.0, 0.0, self.ankle_to_sole_m);
        // u = Rz(ψ_f)ᵀ (c − e)
        let u = Vector3::new(cy * d.x + sy * d.y, -sy * d.x + cy * d.y, d.z);
        let cos_knee = (u.norm_squared() - a * a - b * b) / (2.0 * a * b);
        if !(-1.0..=1.0 + LIMIT_SLACK).contains(&cos_knee) {
            return None;
        }
        let knee = cos_knee.min(1.0).acos();
        let ankle_roll = u.y.atan2(u.z);
        if !inside(3, knee) || !inside(5, ankle_roll) {
            return None;
        }
        let wz = (u.y * u.y + u.z * u.z).sqrt();
        let ankle_pitch = (-a * knee.sin()).atan2(a * knee.cos() + b) - u.x.atan2(wz);
        if !inside(4, ankle_pitch) {
            return None;
        }
        // R_hip = Rz(ψ_f) · Rx(−ankle roll) · Ry(−(knee + ankle pitch)); only its third row and
        // second column are needed.
        let (sr, cr) = (-ankle_roll).sin_cos();
        let (sp, cp) = (-(knee + ankle_pitch)).sin_cos();
        // Rx(φ)·Ry(θ) = [[cθ, 0, sθ], [sφ sθ, cφ, −sφ cθ], [−cφ sθ, sφ, cφ cθ]]
        let (m20, m21, m22) = (-cr * sp, sr, cr * cp);
        let (m01, m11) = (-sy * cr, cy * cr);
        let hip_roll = m21.clamp(-1.0, 1.0).asin();
        let hip_pitch = (-m20).atan2(m22);
        let hip_yaw = (-m01).atan2(m11);
        (inside(0, hip_yaw) && inside(1, hip_roll) && inside(2, hip_pitch)).then_some([
            hip_yaw,
            hip_roll,
            hip_pitch,
            knee,
            ankle_pitch,
            ankle_roll,
        ])
    }

    /// The closed-form solution without the joint-limit check.
    fn ik_unlimited(&self, sole_in_base: &Vector3<f64>, foot_yaw: f64) -> Option<[f64; 6]> {
        self.solve(sole_in_base, foot_yaw, false)
    }

    /// The URDF joint positions of an IK solution, by name (the other leg's joints at zero).
    pub fn joint_positions(&self, q: &[f64; 6]) -> HashMap<String, f64> {
        let mut positions: HashMap<String, f64> = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect();
        for (joint, value) in LEG_JOINTS.iter().zip(q) {
            positions.insert(format!("{}_{joint}", self.side.prefix()), *value);
        }
        positions
    }

    /// Solves a few targets and compares them with the URDF's forward kinematics: the solver is only
    /// used on a model whose axes it matches.
    fn check_against(&self, model: &RobotModel) -> Result<(), RouteError> {
        let h = self.hip_in_base;
        let down = self.length_m() * 0.8 + self.ankle_to_sole_m;
        let targets = [
            (Vector3::new(0.03, 0.0, -down), 0.0),
            (Vector3::new(-0.02, 0.015, -down + 0.02), 0.3),
            (Vector3::new(0.04, -0.01, -down + 0.03), -0.2),
        ];
        for (offset, yaw) in targets {
            let target = h + offset;
            let q = self
                .ik_unlimited(&target, yaw)
                .ok_or_else(|| RouteError::Robot(format!("{} leg: no IK solution for a reachable check pose", self.side.prefix())))?;
            let foot =
                model.root_from_link(self.side.sole_link(), &self.joint_positions(&q)).map_err(|e| RouteError::Robot(e.to_string()))?;
            let position_error = (foot.translation.vector - target).norm();
            let expected = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
            let rotation_error = (foot.rotation.to_rotation_matrix().matrix() - expected.matrix()).norm();
            if position_error > 1e-6 || rotation_error > 1e-6 {
                return Err(RouteError::Robot(format!(
                    "{} leg: the joint axes differ from the DARwIn-OP form (IK check off by {position_error:.2e} m, {rotation_error:.2e} in rotation)",
                    self.side.prefix()
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn rpbp() -> RobotModel {
        RobotModel::from_urdf_str(patchwalk_robot_model::RPBP_URDF).unwrap()
    }

    #[test]
    fn rpbp_leg_geometry_comes_from_the_urdf() {
        let model = rpbp();
        let left = LegModel::from_robot(&model, Side::Left).unwrap();
        let right = LegModel::from_robot(&model, Side::Right).unwrap();
        assert!((left.hip_in_base - Vector3::new(0.0, 0.037, -0.060)).norm() < 1e-12);
        assert!((right.hip_in_base - Vector3::new(0.0, -0.037, -0.060)).norm() < 1e-12);
        assert!((left.thigh_m - 0.100).abs() < 1e-12 && (left.shin_m - 0.100).abs() < 1e-12);
        assert!((left.ankle_to_sole_m - 0.035).abs() < 1e-12);
        assert_eq!(left.limits[3], JointLimits { lower: 0.0, upper: 2.4 });
        // knee at 2.4 rad: |c − e| = √(2·0.01·(1 + cos 2.4)) = 0.0725 m
        assert!((left.min_length_m() - 0.2 * (1.2f64).cos()).abs() < 1e-12);
    }

    /// Random reachable sole poses: the IK's joint angles put the URDF's sole frame exactly there.
    #[test]
    fn ik_matches_the_urdf_forward_kinematics() {
        let model = rpbp();
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        for side in [Side::Left, Side::Right] {
            let leg = LegModel::from_robot(&model, side).unwrap();
            let mut solved = 0;
            for _ in 0..400 {
                let target = leg.hip_in_base
                    + Vector3::new(rng.random_range(-0.12..0.12), rng.random_range(-0.1..0.1), rng.random_range(-0.235..-0.12));
                let yaw = rng.random_range(-1.0..1.0);
                if let Some(q) = leg.ik(&target, yaw) {
                    solved += 1;
                    let foot = model.root_from_link(side.sole_link(), &leg.joint_positions(&q)).unwrap();
                    assert!((foot.translation.vector - target).norm() < 1e-9, "{side:?} {target:?}");
                    let z = foot.rotation * Vector3::z();
                    assert!((z - Vector3::z()).norm() < 1e-9, "sole not level");
                }
            }
            assert!(solved > 100, "{side:?}: only {solved} of 400 solved");
        }
    }

    #[test]
    fn known_positions_are_reachable_or_not() {
        let leg = LegModel::from_robot(&rpbp(), Side::Left).unwrap();
        // Straight below the hip at the full leg: knee 0, every joint 0.
        let straight = leg.ik(&Vector3::new(0.0, 0.037, -0.295), 0.0).unwrap();
        assert!(straight.iter().all(|q| q.abs() < 1e-6), "{straight:?}");
        // 1 cm below the straight leg: out of reach.
        assert!(leg.ik(&Vector3::new(0.0, 0.037, -0.305), 0.0).is_none());
        // Crouched, 5 cm ahead: reachable with a bent knee.
        let crouch = leg.ik(&Vector3::new(0.05, 0.037, -0.24), 0.0).unwrap();
        assert!(crouch[3] > 0.3);
        // The left foot far to the right (under the right hip and beyond): hip roll limit (−0.8) and reach.
        assert!(leg.ik(&Vector3::new(0.0, -0.15, -0.22), 0.0).is_none());
        // Turned beyond the hip yaw limit (1.2 rad).
        assert!(leg.ik(&Vector3::new(0.0, 0.037, -0.25), 1.4).is_none());
        assert!(leg.ik(&Vector3::new(0.0, 0.037, -0.25), 1.1).is_some());
    }

    #[test]
    fn a_leg_of_another_form_is_refused() {
        // Knee offset forward: not the DARwIn-OP form.
        let urdf = patchwalk_robot_model::RPBP_URDF.replace(
            "<parent link=\"l_thigh\"/><child link=\"l_shin\"/>\n    <origin xyz=\"0 0 -0.100\"",
            "<parent link=\"l_thigh\"/><child link=\"l_shin\"/>\n    <origin xyz=\"0.02 0 -0.100\"",
        );
        assert_ne!(urdf, patchwalk_robot_model::RPBP_URDF);
        let model = RobotModel::from_urdf_str(&urdf).unwrap();
        let err = LegModel::from_robot(&model, Side::Left).unwrap_err();
        assert!(err.to_string().contains("thigh"), "{err}");
        assert!(LegModel::from_robot(&model, Side::Right).is_ok());
    }
}

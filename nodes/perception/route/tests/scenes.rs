//! Scenes with a known passable and impassable region (synthetic heightfields): a flat ground cut by
//! a trench 0.40 m wide (wider than the RPBP can straddle), with and without a bridge, and a rock
//! field. The route must reach the goal, never stand in the trench, cross only over the bridge, and
//! a trench without a bridge must give a clear "no route" error.

use patchwalk_route::synthetic::Terrain;
use patchwalk_route::{Hold, Planner, RouteError, Target};

fn target(x: f64, y: f64) -> Target {
    Target { x, y, z: None }
}

#[test]
fn the_route_goes_around_the_trench_over_the_bridge() {
    let terrain = Terrain::trench(Some(0.15));
    let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 1));
    let planner = Planner::rpbp().unwrap();
    let route = planner.plan(&grid, &holds, Some(target(0.15, -0.2)), target(1.05, -0.2)).unwrap();
    let last = route.body_path.last().unwrap();
    assert!(((last[0] - 1.05).powi(2) + (last[1] + 0.2).powi(2)).sqrt() <= planner.config.snap_m, "ends at {last:?}");
    // Over the trench's x range the body is on the bridge.
    for p in &route.body_path {
        if p[0] > 0.45 && p[0] < 0.85 {
            assert!(p[1] >= 0.15, "body over the trench at {p:?}");
            assert_eq!(p[2], 0.0);
        }
    }
    // Every foot stands on walkable ground, none in the trench.
    for s in &route.stances {
        for foot in [s.left, s.right] {
            assert!(foot[2].abs() < 1e-9, "foot in the trench: {foot:?}");
        }
        assert!(s.flex > 0.0 && s.flex <= 1.0);
    }
    assert!(route.stances.len() >= 3, "{} stances", route.stances.len());
    assert_eq!(route.stats.clusters, 30);
    // The detour is longer than the straight 0.9 m.
    assert!(route.length_m > 1.0, "{}", route.length_m);
    // Deterministic.
    assert_eq!(planner.plan(&grid, &holds, Some(target(0.15, -0.2)), target(1.05, -0.2)).unwrap().stances, route.stances);
}

#[test]
fn a_trench_without_a_bridge_has_no_route() {
    let terrain = Terrain::trench(None);
    let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 1));
    let planner = Planner::rpbp().unwrap();
    let err = planner.plan(&grid, &holds, Some(target(0.15, -0.2)), target(1.05, -0.2)).unwrap_err();
    assert!(matches!(err, RouteError::NoRoute { .. }), "{err}");
    assert!(err.to_string().contains("no route"), "{err}");
    // The near side alone is fine.
    assert!(planner.plan(&grid, &holds, Some(target(0.15, -0.2)), target(0.3, 0.2)).is_ok());
}

#[test]
fn a_rock_field_is_crossed() {
    let terrain = Terrain::rock_field(10, 3);
    let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 5));
    let planner = Planner::rpbp().unwrap();
    let route = planner.plan(&grid, &holds, None, target(1.05, 0.0)).unwrap();
    assert!(route.body_path.len() > 10);
    for s in &route.stances {
        for foot in [s.left, s.right] {
            assert!(terrain.walkable(foot[0], foot[1]) || (foot[2] - terrain.height(foot[0], foot[1])).abs() < 0.03, "{foot:?}");
        }
    }
}

#[test]
fn bad_input_gives_clear_errors() {
    let terrain = Terrain::trench(Some(0.15));
    let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 1));
    let planner = Planner::rpbp().unwrap();
    let (start, goal) = (Some(target(0.15, -0.2)), target(1.05, -0.2));
    assert_eq!(planner.plan(&grid, &[], start, goal), Err(RouteError::NoHolds));
    let mut nan = holds.clone();
    nan[7].position[1] = f64::NAN;
    let err = planner.plan(&grid, &nan, start, goal).unwrap_err();
    assert!(matches!(err, RouteError::NonFiniteHold { index: 7, .. }), "{err}");
    // Goal 2 m beyond the observed terrain.
    let err = planner.plan(&grid, &holds, start, target(3.0, 0.0)).unwrap_err();
    assert!(matches!(err, RouteError::OutsideTerrain { what: "goal", .. }), "{err}");
    assert!(err.to_string().contains("outside the observed terrain"), "{err}");
    // Goal on observed ground beyond the trench where no hold was found: nowhere to stand.
    let near_side: Vec<Hold> = holds.iter().copied().filter(|h| h.position[0] < 0.85).collect();
    let err = planner.plan(&grid, &near_side, start, target(1.12, -0.25)).unwrap_err();
    assert!(matches!(err, RouteError::NoStance { what: "goal", .. }), "{err}");
    let err = planner.plan(&grid, &holds, start, target(f64::NAN, 0.0)).unwrap_err();
    assert!(matches!(err, RouteError::NonFinitePoint { what: "goal", .. }), "{err}");
    // Holds far from the terrain: no stance anywhere.
    let far: Vec<Hold> = holds.iter().map(|h| Hold { position: [h.position[0] + 10.0, h.position[1], 0.0], score: h.score }).collect();
    assert!(matches!(planner.plan(&grid, &far, start, goal), Err(RouteError::NoStanceAnywhere { .. })));
    // A bad parameter is named.
    let config = patchwalk_route::PlannerConfig { thinning_m: -1.0, ..Default::default() };
    let err = Planner::new(planner.biped.clone(), config).unwrap_err();
    assert!(err.to_string().contains("thinning_m"), "{err}");
}

//! Planning time per frame of the coarse route planner (CNN IV) on synthetic 60 × 80 terrains: a
//! trench with a bridge (a detour), a trench without one (no route) and rock fields; prints the
//! milliseconds per plan (median and max over the runs) split into clustering, stances (Flex at
//! every vertex) and search, with the route length and stance count.
//!
//! `bench_route [RUNS]` (default 5). Also prints the process CPU time per plan, which a loaded
//! shared host does not inflate.

use std::time::Instant;

use patchwalk_route::synthetic::Terrain;
use patchwalk_route::{Planner, Target};

fn main() -> anyhow::Result<()> {
    let runs: usize = match std::env::args().nth(1) {
        Some(s) => s.parse().map_err(|e| anyhow::anyhow!("RUNS must be a positive integer, got {s:?}: {e}"))?,
        None => 5,
    };
    let runs = runs.max(1);
    let planner = Planner::rpbp()?;
    let target = |x: f64, y: f64| Target { x, y, z: None };
    let scenes = [
        ("trench + bridge", Terrain::trench(Some(0.15)), Some(target(0.15, -0.2)), target(1.05, -0.2)),
        ("trench (no route)", Terrain::trench(None), Some(target(0.15, -0.2)), target(1.05, -0.2)),
        ("rock field 10", Terrain::rock_field(10, 3), None, target(1.05, 0.0)),
        ("rock field 20", Terrain::rock_field(20, 8), None, target(1.05, 0.1)),
    ];
    println!(
        "coarse route planner (CNN IV), 60 x 80 grid, k = {}, {} x {} workspace samples, {} threads, {runs} runs",
        planner.config.clusters,
        planner.config.height_samples,
        planner.config.yaw_samples,
        rayon::current_num_threads()
    );
    println!(
        "{:<18} {:>6} {:>8} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8} {:>7}",
        "scene", "holds", "stance v", "total ms", "max ms", "kmeans", "stances", "search", "length", "stances", "cpu ms"
    );
    for (name, terrain, start, goal) in scenes {
        let (grid, holds) = (terrain.grid(), terrain.holds(0.03, 1));
        let mut totals = Vec::new();
        let mut last = None;
        let cpu0 = process_cpu_ms();
        for _ in 0..runs {
            let t = Instant::now();
            let result = planner.plan(&grid, &holds, start, goal);
            totals.push(t.elapsed().as_secs_f64() * 1e3);
            last = Some(result);
        }
        let cpu = match (cpu0, process_cpu_ms()) {
            (Some(a), Some(b)) => format!("{:.0}", (b - a) / runs as f64),
            _ => "n/a".to_string(),
        };
        totals.sort_by(f64::total_cmp);
        let median = totals[totals.len() / 2];
        let max = totals[totals.len() - 1];
        match last {
            Some(Ok(route)) => println!(
                "{name:<18} {:>6} {:>8} {median:>9.1} {max:>9.1} {:>9.1} {:>9.1} {:>9.2} {:>7.2}m {:>8} {cpu:>7}",
                holds.len(),
                route.stats.vertices_with_stance,
                route.stats.cluster_ms,
                route.stats.stance_ms,
                route.stats.search_ms,
                route.length_m,
                route.stances.len()
            ),
            Some(Err(e)) => println!("{name:<18} {:>6} {:>8} {median:>9.1} {max:>9.1}   cpu {cpu} ms ({e})", holds.len(), "-"),
            None => {}
        }
    }
    println!(
        "total/max ms: wall clock per plan; cpu ms: process CPU time per plan (all threads; the wall clock on a shared host is longer)"
    );
    Ok(())
}

/// CPU time of this process so far (user + system, ms), from /proc/self/stat (Linux).
fn process_cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the ")" closing the command name: state is field 3, utime 14, stime 15.
    let rest = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // Linux reports these in USER_HZ = 100 ticks per second.
    Some((utime + stime) * 10.0)
}

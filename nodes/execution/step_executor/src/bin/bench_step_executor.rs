//! Benchmarks of the step executor (prints numbers; no asserts):
//! 1. matching 1,000 map patches × 100 trained motions (J 6.3 matcher; target ≤ 0.1 ms);
//! 2. control-cycle period and jitter of the bus thread on the simulated pty bus (target 8 ms, p99
//!    jitter ≤ 1 ms), at load 0 and with 4 busy-loop processes started by the bench (killed after);
//! 3. time of one 12-servo sync write + sync read round trip through dynamixel2 on the pty bus;
//! 4. e-stop → hold time on a slow bus (200 ms answers inside a 500 ms budget, slow-bus fault off
//!    so that the motion keeps playing): a stop never waits behind more than one transaction.
//!
//! Run: `cargo run --release -p step_executor --bin bench_step_executor` (from the repository root).
//! The bus thread asks for SCHED_FIFO (root or CAP_SYS_NICE); without it the numbers under load
//! are those of nice -15 (the bench prints which).

use std::time::{Duration, Instant};

use anyhow::Context as _;

use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::{self};
use patchwalk_dynamixel::sim_chain::{SimChain, SimConfig};
use patchwalk_robot_model::kinematics::RobotModel;
use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};
use step_executor::config::{StepExecutorConfig, DEFAULT_JOINTS};
use step_executor::executor::{initialise_bus, Executor, LoopSettings};
use step_executor::library::{Keyframe, Motion};
use step_executor::matcher::{Matcher, MatcherConfig};
use step_executor::player::{JointSpec, Player, PlayerEvent};

/// Small deterministic generator (xorshift64*), seeded.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
}

fn random_patch(rng: &mut Rng) -> anyhow::Result<Patch> {
    let kinds = [
        (SurfaceType::EllipticParaboloid, BoundaryType::Ellipse, 2),
        (SurfaceType::HyperbolicParaboloid, BoundaryType::Ellipse, 2),
        (SurfaceType::CylindricParaboloid, BoundaryType::Rectangle, 2),
        (SurfaceType::CircularParaboloid, BoundaryType::Circle, 1),
        (SurfaceType::Plane, BoundaryType::Rectangle, 2),
    ];
    let (surface, boundary, nd) = kinds[(rng.next_f64() * kinds.len() as f64) as usize % kinds.len()];
    let d = (0..nd).map(|_| rng.uniform(0.02, 0.06)).collect();
    let k = nalgebra::Vector2::new(rng.uniform(-30.0, 30.0), rng.uniform(-30.0, 30.0));
    let r = nalgebra::Vector3::new(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-3.0, 3.0));
    // The area around the feet, ~10 cm in front of the robot (J 6.3), in base_link.
    let c = nalgebra::Vector3::new(rng.uniform(0.05, 0.35), rng.uniform(-0.15, 0.15), rng.uniform(-0.32, -0.26));
    Ok(Patch::new(surface, boundary, d, k, r, c)?)
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let index = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[index.min(sorted.len() - 1)]
}

fn summary(name: &str, unit: &str, mut values: Vec<f64>) {
    values.sort_by(f64::total_cmp);
    let mean = values.iter().sum::<f64>() / values.len().max(1) as f64;
    println!(
        "{name}: n={} mean={mean:.4}{unit} median={:.4}{unit} p95={:.4}{unit} p99={:.4}{unit} max={:.4}{unit}",
        values.len(),
        percentile(&values, 0.5),
        percentile(&values, 0.95),
        percentile(&values, 0.99),
        values.last().copied().unwrap_or(f64::NAN)
    );
}

fn bench_matching() -> anyhow::Result<()> {
    let mut rng = Rng(0x5EED_1234_ABCD_0001);
    let trained = (0..100).map(|_| random_patch(&mut rng)).collect::<anyhow::Result<Vec<Patch>>>()?;
    let mut map = (0..1000).map(|_| random_patch(&mut rng)).collect::<anyhow::Result<Vec<Patch>>>()?;
    // A few map patches are noisy re-observations of trained ones (within the thresholds).
    for (i, slot) in map.iter_mut().step_by(97).enumerate() {
        let mut seen = trained[i * 7 % trained.len()].clone();
        seen.center.x += 0.003;
        seen.boundary_params[0] += 0.005;
        *slot = seen;
    }
    let matcher = Matcher::new(MatcherConfig::default(), &trained);
    let mut times = Vec::new();
    let mut found = None;
    for _ in 0..2000 {
        let start = Instant::now();
        found = std::hint::black_box(matcher.best_match(std::hint::black_box(&map)));
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    summary("matching best_match 1000 map x 100 trained", " ms", times);
    println!("  best match: {found:?}");
    let mut times = Vec::new();
    for _ in 0..50 {
        let start = Instant::now();
        std::hint::black_box(matcher.report(std::hint::black_box(&map)));
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    summary("matching report (best + 3 nearest misses, all pairs)", " ms", times);
    Ok(())
}

fn joint_specs(config: &StepExecutorConfig) -> anyhow::Result<Vec<JointSpec>> {
    let model = RobotModel::from_file(&config.urdf_path).context("load URDF (run from the repository root)")?;
    config
        .servos
        .iter()
        .map(|servo| {
            let limits = model.joint_limits(&servo.joint)?.context("joint without limits")?;
            Ok(JointSpec { servo: servo.clone(), limits })
        })
        .collect()
}

fn sim_bus() -> anyhow::Result<(SimChain, DynamixelBus)> {
    let chain = SimChain::spawn(SimConfig::with_servos(12))?;
    let bus = DynamixelBus::open(&chain.device_path(), 1_000_000)?;
    Ok((chain, bus))
}

fn bench_round_trip(config: &StepExecutorConfig, specs: &[JointSpec]) -> anyhow::Result<()> {
    let (_chain, mut bus) = sim_bus()?;
    let player = Player::new(config.player.clone(), specs.to_vec());
    initialise_bus(&mut bus, &player, &config.bus)?;
    let ids: Vec<u8> = specs.iter().map(|s| s.servo.id).collect();
    let mut times = Vec::new();
    for i in 0..1000u32 {
        let goals: Vec<(u8, u32)> = ids.iter().map(|&id| (id, 2048 + (i % 50))).collect();
        let start = Instant::now();
        servo_bus::sync_write_u32(&mut bus, mx28::GOAL_POSITION, &goals)?;
        servo_bus::read_present_positions(&mut bus, &ids).map_err(|(e, _)| e)?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    summary("12-servo sync write + sync read round trip (pty, 1 Mbps wire time simulated)", " ms", times);
    // Wire time of the same traffic at 1 Mbps: sync write 74 B + sync read instruction 26 B + 12 x 15 B status.
    println!("  (bytes on a real 1 Mbps RS-485 bus: 280 -> {:.2} ms of wire time)", 280.0 * 10.0 / 1e6 * 1e3);
    Ok(())
}

/// `n` busy-loop processes (this binary with `--busy-loop`), killed when dropped.
struct Load(Vec<std::process::Child>);

impl Load {
    fn start(n: usize) -> anyhow::Result<Self> {
        let exe = std::env::current_exe()?;
        let children = (0..n).map(|_| std::process::Command::new(&exe).arg("--busy-loop").spawn()).collect::<Result<Vec<_>, _>>()?;
        Ok(Self(children))
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        for child in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A motion on a level disc: one keyframe per joint angle (rad, every joint alike), each moved to in
/// `move_s` and held `pause_s`.
fn bench_motion(name: &str, angles: &[f64], move_s: f64, pause_s: f64) -> anyhow::Result<Motion> {
    Ok(Motion {
        name: name.into(),
        patch: Patch::level_disc(0.02, nalgebra::Vector3::new(0.1, 0.0, -0.29))?,
        keyframes: angles.iter().map(|&q| Keyframe { positions: vec![q; DEFAULT_JOINTS.len()], move_s, pause_s }).collect(),
    })
}

fn bench_control_cycle(config: &StepExecutorConfig, specs: &[JointSpec], load: usize) -> anyhow::Result<()> {
    let (_chain, mut bus) = sim_bus()?;
    let player = Player::new(config.player.clone(), specs.to_vec());
    initialise_bus(&mut bus, &player, &config.bus)?;
    let _load = Load::start(load)?;
    std::thread::sleep(Duration::from_millis(200));
    let executor = Executor::spawn(Box::new(bus), player, LoopSettings::from_config(config))?;
    // Ankle/knee-safe small amplitude inside every joint's limits.
    let motion = bench_motion("bench", &[0.3, 0.1, 0.4, 0.2], 1.0, 0.2)?;
    // Let the loop learn the present pose, then play ~4.8 s.
    std::thread::sleep(Duration::from_millis(100));
    executor.play(motion)?;
    let mut starts = Vec::new();
    let mut busy = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let t = executor.telemetry().recv_timeout(Duration::from_secs(1))?;
        if let Some(PlayerEvent::Fault(fault)) = &t.event {
            anyhow::bail!("fault during the benchmark: {fault}");
        }
        if matches!(t.state, step_executor::player::PlayerState::Playing { .. }) {
            starts.push(t.started);
            busy.push(t.busy.as_secs_f64() * 1e3);
        }
        if matches!(t.event, Some(PlayerEvent::Finished { .. })) || Instant::now() > deadline {
            break;
        }
    }
    let periods: Vec<f64> = starts.windows(2).map(|w| (w[1] - w[0]).as_secs_f64() * 1e3).collect();
    let target = config.player.cycle_ms;
    let jitter: Vec<f64> = periods.iter().map(|p| (p - target).abs()).collect();
    let health = executor.health();
    println!("control cycle at load {load} ({load} busy-loop processes; bus thread: {}):", health.scheduling);
    summary("  control cycle period (target 8 ms)", " ms", periods);
    summary("  control cycle |period - 8 ms| jitter", " ms", jitter);
    summary("  control cycle bus time (sync write + sync read + hold logic)", " ms", busy);
    println!(
        "  bus health: {:.1} cycles/s of {:.0}, period p50 {:.3} ms p99 {:.3} ms, deadline misses {}",
        health.cycle_rate_hz, health.nominal_rate_hz, health.cycle_period_p50_ms, health.cycle_period_p99_ms, health.deadline_misses
    );
    Ok(())
}

fn bench_estop_on_slow_bus(config: &StepExecutorConfig, specs: &[JointSpec]) -> anyhow::Result<()> {
    let (chain, bus) = sim_bus()?;
    let mut bus = bus.with_response_timeout(Duration::from_millis(500));
    let player = Player::new(config.player.clone(), specs.to_vec());
    initialise_bus(&mut bus, &player, &config.bus)?;
    let mut settings = LoopSettings::from_config(config);
    settings.slow_bus.consecutive_misses = 0;
    settings.slow_bus.min_rate_percent = 0.0;
    let executor = Executor::spawn(Box::new(bus), player, settings)?;
    std::thread::sleep(Duration::from_millis(100));
    chain.set_faults(|f| f.latency = Duration::from_millis(200));
    let motion = bench_motion("slow", &[0.3], 20.0, 0.0)?;
    let mut rng = Rng(0x5EED_0000_E570_0001);
    let mut times = Vec::new();
    for _ in 0..8 {
        executor.play(motion.clone())?;
        // Into the motion, then a stop at a random point of a cycle.
        let mut playing = 0;
        while playing < 2 {
            if executor.telemetry().recv_timeout(Duration::from_secs(5))?.goal.is_some() {
                playing += 1;
            }
        }
        std::thread::sleep(Duration::from_secs_f64(rng.uniform(0.0, 0.2)));
        while executor.telemetry().try_recv().is_ok() {}
        let asked = Instant::now();
        executor.estop();
        loop {
            let t = executor.telemetry().recv_timeout(Duration::from_secs(5))?;
            if t.event == Some(PlayerEvent::EStopped) {
                times.push(asked.elapsed().as_secs_f64() * 1e3);
                break;
            }
        }
    }
    summary("e-stop -> hold on a slow bus (200 ms answers, one transaction = one sync read)", " ms", times);
    Ok(())
}

fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--busy-loop") {
        // A load process for the cycle benchmark: spin until killed.
        let mut x = 0u64;
        loop {
            x = std::hint::black_box(x.wrapping_add(1));
        }
    }
    let config: StepExecutorConfig = patchwalk_ros::params::load_config(Some(std::path::Path::new("config/step_executor.yaml")), &[])
        .context("run from the repository root (reads config/step_executor.yaml and urdf/rpbp.urdf)")?;
    let specs = joint_specs(&config)?;
    bench_matching()?;
    bench_round_trip(&config, &specs)?;
    bench_control_cycle(&config, &specs, 0)?;
    bench_control_cycle(&config, &specs, 4)?;
    bench_estop_on_slow_bus(&config, &specs)?;
    Ok(())
}

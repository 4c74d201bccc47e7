//! Benchmarks of the step executor (prints numbers; no asserts):
//! 1. matching 1,000 map patches × 100 trained motions (J 6.3 matcher; target ≤ 0.1 ms);
//! 2. control-cycle period and jitter of the bus thread on the simulated pty bus (target 8 ms, p99
//!    jitter ≤ 1 ms), at load 0 and with 4 busy-loop processes started by the bench (killed after),
//!    with the host's load average printed before and after each run;
//! 3. time of one 12-servo sync write + sync read round trip through dynamixel2 on the pty bus;
//! 4. e-stop → hold time (the stop's cycle as the node sees it) on the pty bus at each load (within
//!    one 8 ms cycle), and on a slow bus (200 ms answers inside a 500 ms budget, slow-bus fault off
//!    so that the motion keeps playing): a stop never waits behind more than one transaction.
//!
//! Run: `cargo run --release -p step_executor --bin bench_step_executor` (from the repository root);
//! `-- --cycle-only` runs the cycle benchmark alone, `--load 0 --load 4` sets its runs (busy-loop
//! processes), `--load-nice 19` starts them under `nice -n 19`, `--seconds 20` plays longer, and
//! `--realtime-priority 0` measures the fallback without SCHED_FIFO (nice -15).
//! The bus thread asks for SCHED_FIFO (root or CAP_SYS_NICE); without it the numbers under load
//! are those of nice -15 (the bench prints which).

use std::time::{Duration, Instant};

use anyhow::Context as _;
use clap::Parser;

use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::mock::MockBus;
use patchwalk_dynamixel::servo_bus::{self, ServoBus};
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
    let player = Player::new(config.player.clone(), specs.to_vec())?;
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

#[derive(Parser, Debug)]
#[command(about = "step_executor benchmarks: matching, bus round trip, control-cycle jitter, e-stop on a slow bus")]
struct Args {
    /// Only the control-cycle benchmark.
    #[arg(long)]
    cycle_only: bool,
    /// Busy-loop processes of one control-cycle run (repeat the flag for more runs).
    #[arg(long = "load", default_values_t = [0usize, 4])]
    loads: Vec<usize>,
    /// Niceness of the busy-loop processes (`nice -n`).
    #[arg(long, default_value_t = 0)]
    load_nice: i32,
    /// The bus of the control-cycle runs: `sim` (the Protocol 2.0 master on the simulated pty
    /// chain) or `mock` (in memory: the cycle's scheduling alone, without the pty's kernel path).
    #[arg(long, default_value = "sim", value_parser = ["sim", "mock"])]
    bus: String,
    /// Seconds of motion per control-cycle run (multiples of 1.2 s).
    #[arg(long, default_value_t = 4.8)]
    seconds: f64,
    /// The bus thread's SCHED_FIFO priority (default: `bus.realtime_priority` of the config; 0 =
    /// not asked, the thread runs at nice -15).
    #[arg(long)]
    realtime_priority: Option<i32>,
    /// Spin until killed (a load process of the cycle benchmark).
    #[arg(long, hide = true)]
    busy_loop: bool,
}

/// The host's load average (1, 5, 15 min) as `/proc/loadavg` shows it.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// `n` busy-loop processes (this binary with `--busy-loop`, under `nice -n nice`), killed when dropped.
struct Load(Vec<std::process::Child>);

impl Load {
    fn start(n: usize, nice: i32) -> anyhow::Result<Self> {
        let exe = std::env::current_exe()?;
        let spawn = || {
            if nice == 0 {
                std::process::Command::new(&exe).arg("--busy-loop").spawn()
            } else {
                std::process::Command::new("nice").arg("-n").arg(nice.to_string()).arg(&exe).arg("--busy-loop").spawn()
            }
        };
        let children = (0..n).map(|_| spawn()).collect::<Result<Vec<_>, _>>()?;
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

fn bench_control_cycle(config: &StepExecutorConfig, specs: &[JointSpec], load: usize, args: &Args) -> anyhow::Result<()> {
    let player = Player::new(config.player.clone(), specs.to_vec())?;
    let mut _chain = None;
    let mut bus: Box<dyn ServoBus> = if args.bus == "mock" {
        let ids: Vec<u8> = specs.iter().map(|s| s.servo.id).collect();
        let mock = MockBus::new(&ids);
        mock.state().log_goal_writes = false;
        Box::new(mock)
    } else {
        let (chain, bus) = sim_bus()?;
        _chain = Some(chain);
        // The chain answers through the kernel's pty path, which runs at normal priority: on a
        // loaded host one answer can lag past RS-485's 34 ms (the tests allow 300 ms for the same
        // reason). A late answer then shows as an overrun in the figures instead of a fault.
        Box::new(bus.with_response_timeout(Duration::from_millis(300)))
    };
    initialise_bus(bus.as_mut(), &player, &config.bus)?;
    let load_before = load_average();
    let _load = Load::start(load, args.load_nice)?;
    std::thread::sleep(Duration::from_millis(200));
    let mut settings = LoopSettings::from_config(config);
    if let Some(priority) = args.realtime_priority {
        settings.realtime_priority = priority;
    }
    // Measured, not tripped: a bus too slow for the cycle shows as overruns in the figures.
    settings.slow_bus.consecutive_misses = 0;
    settings.slow_bus.min_rate_percent = 0.0;
    let executor = Executor::spawn(bus, player, settings)?;
    let keyframe = |q: f64| Keyframe { positions: vec![q; DEFAULT_JOINTS.len()], move_s: 1.0, pause_s: 0.2 };
    // Ankle/knee-safe small amplitude inside every joint's limits.
    let motion = Motion {
        name: "bench".into(),
        patch: Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.02],
            nalgebra::Vector2::zeros(),
            nalgebra::Vector3::zeros(),
            nalgebra::Vector3::new(0.1, 0.0, -0.29),
        )?,
        keyframes: [0.3, 0.1, 0.4, 0.2].into_iter().cycle().take((args.seconds / 1.2).ceil().max(1.0) as usize).map(keyframe).collect(),
    };
    // Let the loop learn the present pose, then play.
    std::thread::sleep(Duration::from_millis(100));
    executor.play(motion)?;
    let mut starts = Vec::new();
    let mut busy = Vec::new();
    let mut wake_late = Vec::new();
    let deadline = Instant::now() + Duration::from_secs_f64(args.seconds * 2.0 + 5.0);
    loop {
        let t = executor.telemetry().recv_timeout(Duration::from_secs(1))?;
        if let Some(PlayerEvent::Fault(fault)) = &t.event {
            anyhow::bail!("fault during the benchmark: {fault}");
        }
        if matches!(t.state, step_executor::player::PlayerState::Playing { .. }) {
            starts.push(t.started);
            busy.push(t.busy.as_secs_f64() * 1e3);
            wake_late.push(t.wake_late.as_secs_f64() * 1e3);
        }
        if matches!(t.event, Some(PlayerEvent::Finished { .. })) || Instant::now() > deadline {
            break;
        }
    }
    let periods: Vec<f64> = starts.windows(2).map(|w| (w[1] - w[0]).as_secs_f64() * 1e3).collect();
    let target = config.player.cycle_ms;
    let jitter: Vec<f64> = periods.iter().map(|p| (p - target).abs()).collect();
    let health = executor.health();
    let nice = if args.load_nice == 0 { String::new() } else { format!(" under nice -n {}", args.load_nice) };
    println!(
        "control cycle on the {} bus with {load} busy-loop processes{nice} (load average before {load_before}, after {}; bus thread: {}):",
        args.bus,
        load_average(),
        health.scheduling
    );
    summary("  control cycle period (target 8 ms)", " ms", periods);
    summary("  control cycle |period - 8 ms| jitter", " ms", jitter);
    summary("  control cycle start after its deadline (wake-up latency; an overrun's excess)", " ms", wake_late);
    summary("  control cycle bus time (sync write + sync read + hold logic)", " ms", busy);
    println!(
        "  bus health: {:.1} cycles/s of {:.0}, period p50 {:.3} ms p99 {:.3} ms, deadline misses {}",
        health.cycle_rate_hz, health.nominal_rate_hz, health.cycle_period_p50_ms, health.cycle_period_p99_ms, health.deadline_misses
    );
    Ok(())
}

/// E-stop → hold (the EStopped cycle as the node sees it) at random points of the cycle, `tries`
/// times, with the chain answering after `latency` and `load` busy-loop processes running.
fn bench_estop(
    config: &StepExecutorConfig,
    specs: &[JointSpec],
    latency: Duration,
    load: usize,
    tries: usize,
    args: &Args,
) -> anyhow::Result<()> {
    let (chain, bus) = sim_bus()?;
    let mut bus = bus.with_response_timeout(Duration::from_millis(500));
    let player = Player::new(config.player.clone(), specs.to_vec())?;
    initialise_bus(&mut bus, &player, &config.bus)?;
    let mut settings = LoopSettings::from_config(config);
    settings.slow_bus.consecutive_misses = 0;
    settings.slow_bus.min_rate_percent = 0.0;
    if let Some(priority) = args.realtime_priority {
        settings.realtime_priority = priority;
    }
    let _load = Load::start(load, args.load_nice)?;
    let executor = Executor::spawn(Box::new(bus), player, settings)?;
    std::thread::sleep(Duration::from_millis(100));
    chain.set_faults(|f| f.latency = latency);
    let keyframe = |q: f64| Keyframe { positions: vec![q; DEFAULT_JOINTS.len()], move_s: 20.0, pause_s: 0.0 };
    let motion = Motion {
        name: "slow".into(),
        patch: Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.02],
            nalgebra::Vector2::zeros(),
            nalgebra::Vector3::zeros(),
            nalgebra::Vector3::new(0.1, 0.0, -0.29),
        )?,
        keyframes: vec![keyframe(0.3)],
    };
    let mut rng = Rng(0x5EED_0000_E570_0001);
    let mut times = Vec::new();
    let cycle_s = config.player.cycle_ms / 1000.0;
    for _ in 0..tries {
        executor.play(motion.clone())?;
        // Into the motion, then a stop at a random point of a cycle.
        let mut playing = 0;
        while playing < 2 {
            if executor.telemetry().recv_timeout(Duration::from_secs(5))?.goal.is_some() {
                playing += 1;
            }
        }
        std::thread::sleep(Duration::from_secs_f64(rng.uniform(0.0, latency.as_secs_f64().max(cycle_s))));
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
    let ms = latency.as_secs_f64() * 1e3;
    if latency.is_zero() {
        summary(&format!("e-stop -> hold ({load} busy-loop processes, load average {})", load_average()), " ms", times);
    } else {
        summary(&format!("e-stop -> hold on a slow bus ({ms:.0} ms answers, one transaction = one sync read)"), " ms", times);
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if args.busy_loop {
        // A load process for the cycle benchmark: spin until killed.
        let mut x = 0u64;
        loop {
            x = std::hint::black_box(x.wrapping_add(1));
        }
    }
    let config: StepExecutorConfig = patchwalk_ros::params::load_config(Some(std::path::Path::new("config/step_executor.yaml")), &[])
        .context("run from the repository root (reads config/step_executor.yaml and urdf/rpbp.urdf)")?;
    let specs = joint_specs(&config)?;
    if !args.cycle_only {
        bench_matching()?;
        bench_round_trip(&config, &specs)?;
    }
    for &load in &args.loads {
        bench_control_cycle(&config, &specs, load, &args)?;
    }
    if !args.cycle_only {
        for &load in &args.loads {
            bench_estop(&config, &specs, Duration::ZERO, load, 50, &args)?;
        }
        bench_estop(&config, &specs, Duration::from_millis(200), 0, 8, &args)?;
    }
    Ok(())
}

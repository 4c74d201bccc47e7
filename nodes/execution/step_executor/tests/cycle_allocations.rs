#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)] // an integration test
// The counting allocator implements `GlobalAlloc`, an unsafe trait, by forwarding to `System`.
#![allow(unsafe_code)]
//! The control cycle allocates nothing after warm-up. This test binary's global allocator counts
//! the heap allocations of "tracked" threads: the test's own thread while it runs player cycles
//! (on the mock, and on the real Protocol 2.0 master over the simulated pty chain), and the bus
//! thread of a running `Executor` (it marks itself from its notify callback, which runs on it
//! after every motion cycle). Each test runs N cycles after a warm-up and asserts 0 allocations.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::mock::MockBus;
use patchwalk_dynamixel::servo_bus::{self, ServoBus};
use patchwalk_dynamixel::sim_chain::{SimChain, SimConfig};
use patchwalk_robot_model::kinematics::JointLimits;
use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};
use step_executor::config::ServoConfig;
use step_executor::executor::{Executor, LoopSettings, Telemetry};
use step_executor::library::{Keyframe, Motion};
use step_executor::player::{JointSpec, Player, PlayerConfig, PlayerEvent, PlayerState};

struct Counting;

static TRACKED_ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Whether this thread's allocations are counted (const-initialised: reading it allocates nothing).
    static TRACKED: Cell<bool> = const { Cell::new(false) };
}

fn count() {
    if TRACKED.try_with(Cell::get).unwrap_or(false) {
        TRACKED_ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    }
}

// SAFETY: every call is forwarded to the system allocator with its own arguments; counting touches
// only an atomic and a const thread-local.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count();
        System.alloc_zeroed(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        System.realloc(ptr, layout, new_size)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// One test at a time: the count is global.
static SERIAL: Mutex<()> = Mutex::new(());

/// Allocations of tracked threads while `f` runs on this (tracked) thread.
fn allocations_in<T>(f: impl FnOnce() -> T) -> (u64, T) {
    let before = TRACKED_ALLOCATIONS.load(Ordering::SeqCst);
    TRACKED.with(|t| t.set(true));
    let result = f();
    TRACKED.with(|t| t.set(false));
    (TRACKED_ALLOCATIONS.load(Ordering::SeqCst) - before, result)
}

fn joints(n: u8) -> Vec<JointSpec> {
    (1..=n)
        .map(|id| JointSpec {
            servo: ServoConfig { joint: format!("j{id}"), id, zero_offset: 0.0, direction: 1 },
            limits: JointLimits { lower: -1.0, upper: 1.0 },
        })
        .collect()
}

fn motion(n: usize, seconds: f64) -> Motion {
    let frame = |q: f64| Keyframe { positions: vec![q; n], move_s: seconds / 2.0, pause_s: 0.0 };
    Motion {
        name: "step".into(),
        patch: Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.02],
            nalgebra::Vector2::zeros(),
            nalgebra::Vector3::zeros(),
            nalgebra::Vector3::new(0.1, 0.0, -0.28),
        )
        .unwrap(),
        keyframes: vec![frame(0.4), frame(-0.2)],
    }
}

fn torque_on(bus: &mut dyn ServoBus, n: u8) {
    servo_bus::sync_write_u8(bus, mx28::TORQUE_ENABLE, &(1..=n).map(|id| (id, 1)).collect::<Vec<_>>()).unwrap();
}

/// Idle cycles, a whole motion (start to finish), idle cycles, then a second motion stopped by an
/// e-stop and held: every cycle after the warm-up is counted.
fn play_and_stop(player: &mut Player, bus: &mut dyn ServoBus, n: usize) {
    for _ in 0..5 {
        player.cycle(bus, false);
    }
    // 200 cycles of 8 ms.
    player.start(&motion(n, 1.6)).unwrap();
    player.cycle(bus, false);
    let (allocations, events) = allocations_in(|| {
        let mut events = [false; 3];
        for _ in 0..210 {
            let report = player.cycle(bus, false);
            events[0] |= matches!(report.event, Some(PlayerEvent::Finished { .. }));
        }
        events[1] = matches!(player.state(), PlayerState::Idle);
        events
    });
    assert_eq!(events[..2], [true, true], "the motion played to its end");
    assert_eq!(allocations, 0, "allocations in 210 cycles of a motion");
    player.start(&motion(n, 1.6)).unwrap();
    player.cycle(bus, false);
    let (allocations, stopped) = allocations_in(|| {
        for _ in 0..50 {
            player.cycle(bus, false);
        }
        let stop = player.cycle(bus, true);
        for _ in 0..50 {
            player.cycle(bus, false);
        }
        stop.event == Some(PlayerEvent::EStopped) && matches!(player.state(), PlayerState::Stopped)
    });
    assert!(stopped);
    assert_eq!(allocations, 0, "allocations in 101 cycles around an e-stop");
}

#[test]
fn the_counter_sees_allocations() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let (allocations, _) = allocations_in(|| std::hint::black_box(vec![1u8; 16]));
    assert_eq!(allocations, 1);
}

#[test]
fn player_cycles_on_the_mock_allocate_nothing() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let mut bus = MockBus::new(&(1..=12).collect::<Vec<_>>());
    bus.state().max_step_ticks = 20;
    bus.state().log_goal_writes = false;
    torque_on(&mut bus, 12);
    let mut player = Player::new(PlayerConfig::default(), joints(12)).unwrap();
    play_and_stop(&mut player, &mut bus, 12);
    assert!(bus.state().sync_reads > 300);
}

#[test]
fn player_cycles_on_the_dynamixel_master_over_the_sim_chain_allocate_nothing() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    // The chain runs on its own (untracked) thread; the master and the player on this one.
    let chain = SimChain::spawn(SimConfig::with_servos(12)).unwrap();
    let mut bus = DynamixelBus::open(&chain.device_path(), 1_000_000).unwrap().with_response_timeout(Duration::from_millis(300));
    torque_on(&mut bus, 12);
    let mut player = Player::new(PlayerConfig::default(), joints(12)).unwrap();
    play_and_stop(&mut player, &mut bus, 12);
    assert!(chain.goal_history(1).len() > 250, "every cycle wrote its goals");
}

#[test]
fn bus_thread_cycles_allocate_nothing() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let bus = MockBus::new(&(1..=12).collect::<Vec<_>>());
    bus.state().max_step_ticks = 20;
    bus.state().log_goal_writes = false;
    let player = Player::new(PlayerConfig::default(), joints(12)).unwrap();
    // 2 ms cycles: 25 per health hand-over and vitals read.
    let executor = Executor::spawn(Box::new(bus), player, LoopSettings::new(Duration::from_millis(2))).unwrap();
    // The bus thread marks itself tracked the first time it notifies (after a motion cycle).
    executor.set_notify(Box::new(|| TRACKED.with(|t| t.set(true))));
    let wait = |what: &str, predicate: &dyn Fn(&Telemetry) -> bool| loop {
        let t = executor.telemetry().recv_timeout(Duration::from_secs(10)).unwrap_or_else(|_| panic!("no telemetry: {what}"));
        if predicate(&t) {
            break;
        }
    };
    wait("positions", &|t| t.positions.iter().all(Option::is_some));
    executor.play(motion(12, 20.0)).unwrap();
    wait("a motion cycle", &|t| t.goal.is_some());
    // Warm-up: the health buffers take their texts while the reader takes the newest.
    for _ in 0..6 {
        std::thread::sleep(Duration::from_millis(60));
        executor.health();
    }
    let mut seen: Vec<Telemetry> = Vec::with_capacity(4096);
    let before = TRACKED_ALLOCATIONS.load(Ordering::SeqCst);
    let end = Instant::now() + Duration::from_millis(600);
    let mut stop_at = Some(Instant::now() + Duration::from_millis(400));
    while Instant::now() < end {
        if stop_at.is_some_and(|at| Instant::now() >= at) {
            executor.estop();
            stop_at = None;
        }
        std::thread::sleep(Duration::from_millis(5));
        seen.extend(std::iter::from_fn(|| executor.telemetry().try_recv().ok()).take(seen.capacity() - seen.len()));
    }
    let allocations = TRACKED_ALLOCATIONS.load(Ordering::SeqCst) - before;
    let motion_cycles = seen.iter().filter(|t| t.goal.is_some()).count();
    let stopped = seen.iter().any(|t| t.event == Some(PlayerEvent::EStopped));
    let after_stop = seen.iter().skip_while(|t| t.event != Some(PlayerEvent::EStopped)).count();
    assert!(motion_cycles > 50 && stopped && after_stop > 20, "{motion_cycles} motion cycles, stopped {stopped}, {after_stop} after");
    assert_eq!(allocations, 0, "allocations on the bus thread in {} cycles (a motion, an e-stop, holding)", seen.len());
    // The bus thread is counted: a command (its reply, the torque-off id list) allocates.
    let before = TRACKED_ALLOCATIONS.load(Ordering::SeqCst);
    executor.set_torque(false).unwrap();
    assert!(TRACKED_ALLOCATIONS.load(Ordering::SeqCst) > before, "the bus thread's allocations are not seen");
}

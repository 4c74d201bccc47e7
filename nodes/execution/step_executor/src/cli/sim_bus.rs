//! `step_executor sim-bus`: start a simulated MX-28 (Protocol 2.0) servo chain on a pty, print the
//! device path (first stdout line), and serve until SIGINT/SIGTERM. Any Dynamixel master can open the
//! path (the node's `bus.port`, the ROBOTIS dynamixel-sdk, Dynamixel Wizard via socat...).
//!
//! Faults can be injected at run time with one command per stdin line:
//! `silence <id>|all`, `crc <id>`, `malformed <id>`, `wrongid <id> <claimed id>`, `hwerr <id> <bits>`,
//! `latency <ms>`, `move <id> <ticks>`, `unplug`, `replug`, `clear`. `unplug` closes the pty (the
//! master's I/O fails); `replug` opens a new one with the same servos, prints its path on stdout and
//! re-points `--link` to it, so a master reconnecting to the link finds the chain again.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;

use patchwalk_dynamixel::sim_chain::{SimChain, SimConfig};

/// Arguments of `step_executor sim-bus`.
#[derive(clap::Args, Debug)]
pub struct SimBusArgs {
    /// Number of servos (IDs 1..=N).
    #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(u8).range(1..=252))]
    pub servos: u8,
    /// Baud rate whose wire time is simulated.
    #[arg(long, default_value_t = 1_000_000)]
    pub baud: u32,
    /// Delay answers by their wire time at --baud (off by default: answers come as fast as the pty
    /// allows, which keeps integration tests robust on loaded machines; the bench turns it on).
    #[arg(long)]
    pub wire_time: bool,
    /// Initial Return Delay Time in µs (factory: 500; the node writes its configured value at start-up).
    #[arg(long, default_value_t = 500)]
    pub return_delay_us: u32,
    /// Also create a symlink to the pty at this path (stable name for configs and tests).
    #[arg(long)]
    pub link: Option<PathBuf>,
    /// How long a servo is silent after a REBOOT instruction, ms.
    #[arg(long, default_value_t = 100.0)]
    pub boot_ms: f64,
}

pub fn run(args: SimBusArgs) -> anyhow::Result<()> {
    let return_delay_register =
        u8::try_from(args.return_delay_us / 2).ok().filter(|r| *r <= 254).context("--return-delay-us must be at most 508")?;
    let config = SimConfig {
        ids: (1..=args.servos).collect(),
        baud: args.baud,
        simulate_wire_time: args.wire_time,
        return_delay_register,
        boot_time: Duration::from_secs_f64(args.boot_ms / 1000.0),
    };
    let chain = Arc::new(SimChain::spawn(config).context("starting the simulated servo chain")?);
    if let Some(link) = &args.link {
        let _ = std::fs::remove_file(link);
        std::os::unix::fs::symlink(chain.device_path(), link).with_context(|| format!("creating symlink {}", link.display()))?;
    }
    let stop = Arc::new(AtomicBool::new(false));
    signal_hook::flag::register(signal_hook::consts::SIGINT, Arc::clone(&stop))?;
    signal_hook::flag::register(signal_hook::consts::SIGTERM, Arc::clone(&stop))?;
    {
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "{}", chain.device_path().display())?;
        stdout.flush()?;
    }
    eprintln!(
        "sim-bus: {} simulated MX-28 (model 30) on {} at {} baud; Ctrl-C to stop",
        args.servos,
        chain.device_path().display(),
        args.baud
    );
    if !(args.boot_ms.is_finite() && (0.0..=60_000.0).contains(&args.boot_ms)) {
        anyhow::bail!("--boot-ms must be within 0..=60000, got {}", args.boot_ms);
    }
    let control_chain = Arc::clone(&chain);
    let control_link = args.link.clone();
    // Detached: it ends with the process (stdin may stay open forever).
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            match apply_command(&control_chain, control_link.as_deref(), &line) {
                Ok(done) => eprintln!("sim-bus: {done}"),
                Err(err) => eprintln!("sim-bus: {err}"),
            }
        }
    });
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
    }
    if let Some(link) = &args.link {
        let _ = std::fs::remove_file(link);
    }
    eprintln!("sim-bus: stopped");
    Ok(())
}

/// Parse and apply one fault-injection command.
fn apply_command(chain: &SimChain, link: Option<&std::path::Path>, line: &str) -> anyhow::Result<String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let id = |i: usize| -> anyhow::Result<u8> { words.get(i).context("missing servo id")?.parse().context("servo id must be 1..=252") };
    match words.as_slice() {
        [] => Ok("(empty)".into()),
        ["silence", "all"] => {
            chain.set_faults(|f| f.silent_all = true);
            Ok("whole chain silent".into())
        }
        ["silence", _] => {
            let id = id(1)?;
            chain.set_faults(|f| {
                f.silent.insert(id);
            });
            Ok(format!("servo {id} silent"))
        }
        ["crc", _] => {
            let id = id(1)?;
            chain.set_faults(|f| {
                f.crc_errors.insert(id);
            });
            Ok(format!("servo {id} answers with bad CRCs"))
        }
        ["malformed", _] => {
            let id = id(1)?;
            chain.set_faults(|f| {
                f.malformed.insert(id);
            });
            Ok(format!("servo {id} answers with malformed frames"))
        }
        ["hwerr", _, bits] => {
            let id = id(1)?;
            let bits = parse_u8(bits)?;
            chain.set_hardware_error(id, bits);
            Ok(format!("servo {id} hardware error {bits:#04x}"))
        }
        ["latency", ms] => {
            let ms: u64 = ms.parse().context("latency in ms")?;
            chain.set_faults(|f| f.latency = Duration::from_millis(ms));
            Ok(format!("latency {ms} ms"))
        }
        ["move", _, ticks] => {
            let id = id(1)?;
            let ticks: f64 = ticks.parse().context("ticks")?;
            chain.set_present(id, ticks);
            Ok(format!("servo {id} moved to {ticks}"))
        }
        ["wrongid", _, claimed] => {
            let id = id(1)?;
            let claimed: u8 = claimed.parse().context("claimed id must be 0..=253")?;
            chain.set_faults(|f| {
                f.wrong_id.insert(id, claimed);
            });
            Ok(format!("servo {id} answers as servo {claimed}"))
        }
        ["unplug"] => {
            chain.unplug();
            Ok("unplugged (pty closed)".into())
        }
        ["replug"] => {
            let path = chain.replug().context("replug")?;
            if let Some(link) = link {
                let _ = std::fs::remove_file(link);
                std::os::unix::fs::symlink(&path, link).with_context(|| format!("re-pointing {}", link.display()))?;
            }
            let mut stdout = std::io::stdout().lock();
            writeln!(stdout, "{}", path.display())?;
            stdout.flush()?;
            Ok(format!("plugged in again on {}", path.display()))
        }
        ["clear"] => {
            chain.set_faults(|f| *f = Default::default());
            Ok("faults cleared (hardware errors stay until reboot)".into())
        }
        _ => anyhow::bail!("unknown command {line:?} (silence <id>|all, crc <id>, malformed <id>, wrongid <id> <claimed>, hwerr <id> <bits>, latency <ms>, move <id> <ticks>, unplug, replug, clear)"),
    }
}

fn parse_u8(text: &str) -> anyhow::Result<u8> {
    let parsed = match text.strip_prefix("0x") {
        Some(hex) => u8::from_str_radix(hex, 16),
        None => text.parse(),
    };
    parsed.with_context(|| format!("{text:?} is not a byte"))
}

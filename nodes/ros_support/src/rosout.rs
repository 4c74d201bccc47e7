//! The node's log lines on `/rosout` (`rcl_interfaces/msg/Log`), as rcl forwards its loggers: every
//! `tracing` event the filter lets through (the same lines stderr shows) from the patchwalk crates.
//!
//! [`RosoutLayer`] (installed by [`crate::node::init_tracing_with`], which opens the queue) hands each
//! event to a bounded queue without blocking, so the lines logged before the node exists are kept;
//! [`RosoutForwarder`] (started by [`crate::node::RosNode`]) publishes the queue from a thread of its own. Events of the middleware (`rustdds`, `ros2_client`, `mio`) are not
//! forwarded: publishing them would log again. A full queue drops lines rather than slow the caller.

use std::fmt::Write as _;
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::rcl_interfaces::msg::Log;
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::Context;
use tracing_subscriber::Layer;

/// The topic (rcl's).
pub const ROSOUT_TOPIC: &str = "/rosout";
/// Log lines waiting for the forwarder at most.
pub const QUEUE_DEPTH: usize = 1024;
/// Targets whose events stay off `/rosout`.
const MIDDLEWARE: [&str; 4] = ["rustdds", "ros2_client", "mio", "speedy"];

/// rcl's `/rosout` QoS: reliable, transient local, keep last 1000.
pub fn rosout_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1000 })
}

/// One log line before it becomes a message (the node's name is added by the forwarder).
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    pub stamp: Time,
    pub level: u8,
    pub msg: String,
    pub file: String,
    pub function: String,
    pub line: u32,
}

fn queue() -> &'static Mutex<Option<SyncSender<Record>>> {
    static QUEUE: OnceLock<Mutex<Option<SyncSender<Record>>>> = OnceLock::new();
    QUEUE.get_or_init(|| Mutex::new(None))
}

/// `rcl_interfaces/msg/Log` level of a `tracing` level.
pub fn ros_level(level: &Level) -> u8 {
    match *level {
        Level::ERROR => Log::ERROR,
        Level::WARN => Log::WARN,
        Level::INFO => Log::INFO,
        Level::DEBUG | Level::TRACE => Log::DEBUG,
    }
}

/// The message text of an event: its `message` field, then the other fields as `key=value`; for a
/// `log`-crate record (RustDDS logs through `log`) its real target, file and line.
#[derive(Default)]
struct Text {
    text: String,
    log_target: Option<String>,
    log_file: Option<String>,
    log_line: Option<u32>,
}

impl Visit for Text {
    fn record_u64(&mut self, field: &Field, value: u64) {
        if field.name() == "log.line" {
            self.log_line = u32::try_from(value).ok();
        } else {
            self.record_debug(field, &value);
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name().starts_with("log.") {
            return;
        }
        if field.name() == "message" {
            let rest = std::mem::take(&mut self.text);
            let _ = write!(self.text, "{value:?}");
            if !rest.is_empty() {
                let _ = write!(self.text, " {rest}");
            }
        } else {
            let sep = if self.text.is_empty() { "" } else { " " };
            let _ = write!(self.text, "{sep}{}={value:?}", field.name());
        }
    }

    fn record_str(&mut self, field: &Field, value: &str) {
        match field.name() {
            "log.target" => self.log_target = Some(value.to_string()),
            "log.file" => self.log_file = Some(value.to_string()),
            name if name.starts_with("log.") => {}
            "message" => self.record_debug(field, &format_args!("{value}")),
            name => {
                let sep = if self.text.is_empty() { "" } else { " " };
                let _ = write!(self.text, "{sep}{name}={value}");
            }
        }
    }
}

/// The `tracing` layer that queues events for `/rosout`.
pub struct RosoutLayer;

impl<S: Subscriber> Layer<S> for RosoutLayer {
    fn on_event(&self, event: &Event<'_>, _ctx: Context<'_, S>) {
        let meta = event.metadata();
        let Ok(guard) = queue().lock() else { return };
        let Some(sender) = guard.as_ref() else { return };
        let mut text = Text::default();
        event.record(&mut text);
        let target = text.log_target.clone().unwrap_or_else(|| meta.target().to_string());
        if MIDDLEWARE.iter().any(|m| target.starts_with(m)) {
            return;
        }
        let since_epoch = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
        let record = Record {
            stamp: Time { sec: i32::try_from(since_epoch.as_secs()).unwrap_or(i32::MAX), nanosec: since_epoch.subsec_nanos() },
            level: ros_level(meta.level()),
            msg: text.text,
            file: text.log_file.unwrap_or_else(|| meta.file().unwrap_or_default().to_string()),
            function: target,
            line: text.log_line.or(meta.line()).unwrap_or(0),
        };
        // Full or gone: the line is dropped (stderr has it).
        if let Err(TrySendError::Disconnected(_)) = sender.try_send(record) {
            drop(guard);
            if let Ok(mut guard) = queue().lock() {
                *guard = None;
            }
        }
    }
}

fn pending() -> &'static Mutex<Option<Receiver<Record>>> {
    static PENDING: OnceLock<Mutex<Option<Receiver<Record>>>> = OnceLock::new();
    PENDING.get_or_init(|| Mutex::new(None))
}

/// Opens the queue the layer fills; the receiver goes to the forwarder.
pub fn open_queue() -> Receiver<Record> {
    let (sender, receiver) = std::sync::mpsc::sync_channel(QUEUE_DEPTH);
    if let Ok(mut guard) = queue().lock() {
        *guard = Some(sender);
    }
    receiver
}

/// Starts queueing at process start (the lines before the node is up are forwarded when it is).
pub fn open_early() {
    let receiver = open_queue();
    if let Ok(mut guard) = pending().lock() {
        *guard = Some(receiver);
    }
}

/// The queue opened by [`open_early`], else a new one.
pub fn take_queue() -> Receiver<Record> {
    pending().lock().ok().and_then(|mut guard| guard.take()).unwrap_or_else(open_queue)
}

/// Closes the queue (the forwarder's thread then ends).
pub fn close_queue() {
    if let Ok(mut guard) = queue().lock() {
        *guard = None;
    }
}

/// The `Log` message of a record from node `name`.
pub fn log_message(name: &str, record: Record) -> Log {
    Log {
        stamp: record.stamp,
        level: record.level,
        name: name.to_string(),
        msg: record.msg,
        file: record.file,
        function: record.function,
        line: record.line,
    }
}

/// The thread that publishes the queued lines.
pub struct RosoutForwarder {
    thread: Option<JoinHandle<()>>,
}

impl RosoutForwarder {
    /// Publish every queued line with `publish` until the queue closes.
    pub fn start(name: String, receiver: Receiver<Record>, publish: impl Fn(Log) + Send + 'static) -> std::io::Result<Self> {
        let thread = std::thread::Builder::new().name("rosout".into()).spawn(move || loop {
            match receiver.recv_timeout(Duration::from_millis(200)) {
                Ok(record) => publish(log_message(&name, record)),
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                    let closed = queue().lock().map(|g| g.is_none()).unwrap_or(true);
                    if closed {
                        break;
                    }
                }
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            }
        })?;
        Ok(RosoutForwarder { thread: Some(thread) })
    }
}

impl Drop for RosoutForwarder {
    fn drop(&mut self) {
        close_queue();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracing_subscriber::layer::SubscriberExt;

    #[test]
    fn events_become_log_messages_and_the_middleware_stays_out() {
        let receiver = open_queue();
        let subscriber = tracing_subscriber::registry().with(RosoutLayer);
        tracing::subscriber::with_default(subscriber, || {
            tracing::warn!(frames = 3, "patch map ignored");
            tracing::info!(target: "rustdds::rtps::writer", "not forwarded");
        });
        let record = receiver.try_recv().unwrap();
        assert_eq!(record.level, Log::WARN);
        assert_eq!(record.msg, "patch map ignored frames=3");
        assert!(record.line > 0 && record.file.ends_with("rosout.rs"), "{record:?}");
        assert!(receiver.try_recv().is_err(), "a middleware event was forwarded");
        let msg = log_message("patch_mapper", record);
        assert_eq!(msg.name, "patch_mapper");
        close_queue();
    }
}

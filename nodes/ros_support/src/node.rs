//! Shared ROS 2 node plumbing of the patchwalk binaries (over `ros2-client` / RustDDS):
//! the DDS participant on `ROS_DOMAIN_ID` (loopback-only by default), deliberate QoS presets, typed
//! endpoint creation from [`RosMessage`]/[`RosService`], non-blocking drain/serve helpers that never
//! panic on input, SIGINT/SIGTERM shutdown, `tracing` initialisation and a rate-limited logger.
//!
//! A node's `run` is a short straight sequence: `init_tracing` -> `load_config` -> `RosNode::new` ->
//! create endpoints -> `while !shutdown.requested() { drain, serve, publish, sleep }`.
//!
//! Every endpoint name goes through the node's resolver ([`RosNode::resolve`], rcl's rules in
//! [`crate::names`]): absolute names stay, relative and `~` private ones follow the node's
//! namespace and name (`--ros-args -r __ns:=/robot1`), remaps apply to all of them.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use ros2_client::dds::rustdds::DomainParticipantBuilder;
use ros2_client::dds::{Context, Node, Publisher, Server, ServiceMapping, Subscription};
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use ros2_client::service::RmwRequestId;
use ros2_client::{MessageInfo, Name, NodeName, NodeOptions, ServiceTypeName};

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::interface::{RosMessage, RosService};

use crate::names::NodeNames;
use crate::params::{NodeConfig, ParamError};
use crate::ros_args::{LogLevel, RosArgs, RosArgsError};

/// Environment variable selecting the DDS network (`loopback` or `all`); `--dds-network` overrides it.
pub const DDS_NETWORK_ENV: &str = "PATCHWALK_DDS_NETWORK";

/// Errors of the node plumbing.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("ROS_DOMAIN_ID={value:?} is not a domain id (expected an integer 0..=232)")]
    BadDomainId { value: String },
    #[error("{DDS_NETWORK_ENV}={value:?} is not a DDS network (expected `loopback` or `all`)")]
    BadNetwork { value: String },
    #[error("invalid ROS name {name:?}: {reason}")]
    BadName { name: String, reason: String },
    #[error("cannot create the DDS participant on domain {domain_id}: {reason}")]
    Participant { domain_id: u16, reason: String },
    #[error("cannot create node {name:?}: {reason}")]
    Node { name: String, reason: String },
    #[error("cannot create {what} {name:?}: {reason}")]
    Endpoint { what: &'static str, name: String, reason: String },
    #[error("cannot install the SIGINT/SIGTERM handler: {0}")]
    Signal(#[from] std::io::Error),
    #[error("cannot wait for input readiness: {0}")]
    Wait(std::io::Error),
    #[error("DDS Security: {0}")]
    Security(#[from] crate::security::SecurityError),
}

/// Which network interfaces DDS discovery and traffic use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DdsNetwork {
    /// Only 127.0.0.1 (default): tests, demos and single-machine setups; nothing leaves the host.
    Loopback,
    /// Every interface (RustDDS default): for a robot whose sensors or operator run on other hosts.
    All,
}

impl DdsNetwork {
    /// `--dds-network` if given, else `PATCHWALK_DDS_NETWORK`, else loopback.
    pub fn resolve(flag: Option<DdsNetwork>) -> Result<DdsNetwork, NodeError> {
        if let Some(network) = flag {
            return Ok(network);
        }
        match std::env::var(DDS_NETWORK_ENV) {
            Err(_) => Ok(DdsNetwork::Loopback),
            Ok(value) => match value.trim().to_ascii_lowercase().as_str() {
                "" | "loopback" | "localhost" => Ok(DdsNetwork::Loopback),
                "all" => Ok(DdsNetwork::All),
                _ => Err(NodeError::BadNetwork { value }),
            },
        }
    }
}

/// Command-line options every patchwalk node shares (flattened into each node's `RunArgs`).
///
/// The ROS 2 arguments (`--ros-args ... [--]`, see [`crate::ros_args`]) are taken out of the command
/// line before clap sees it ([`parse_command_line`]) and land in `ros`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct NodeArgs {
    /// YAML parameter file (plain or ROS 2 format); without it the embedded defaults are used.
    /// Applied before the `--ros-args --params-file` files.
    #[arg(long, value_name = "FILE")]
    pub config: Option<std::path::PathBuf>,
    /// Parameter override `dotted.key=value` (value parsed as YAML), applied after the files; repeatable.
    #[arg(short = 'p', long = "param", value_name = "KEY=VALUE")]
    pub params: Vec<String>,
    /// DDS network: `loopback` (default) or `all`. Default from PATCHWALK_DDS_NETWORK.
    #[arg(long, value_enum)]
    pub dds_network: Option<DdsNetwork>,
    /// The `--ros-args` of the command line.
    #[arg(skip)]
    pub ros: RosArgs,
}

impl NodeArgs {
    /// The node's names under `--ros-args` (`__node`, `__ns`, remaps).
    pub fn names(&self, default_name: &str) -> Result<NodeNames, NodeError> {
        NodeNames::new(default_name, &self.ros)
    }

    /// The node's config: `--config`, then every `--params-file` (the blocks for this node), then
    /// `--param` and `-p` in order.
    pub fn load_config<T: serde::de::DeserializeOwned>(&self, names: &NodeNames) -> Result<NodeConfig<T>, ParamError> {
        let files: Vec<&std::path::Path> = self.config.iter().chain(&self.ros.params_files).map(|p| p.as_path()).collect();
        let overrides: Vec<String> = self.params.iter().cloned().chain(self.ros.params.iter().map(|p| p.as_override())).collect();
        crate::params::load_node_config(Some(&names.fully_qualified()), &files, &overrides)
    }
}

/// The command line of a node binary: the `--ros-args` blocks taken out, the rest parsed by clap
/// (which exits with its usage message on a bad option).
pub fn parse_command_line<C: clap::Parser>() -> Result<(C, RosArgs), RosArgsError> {
    let (rest, ros) = crate::ros_args::split(std::env::args_os())?;
    Ok((C::parse_from(rest), ros))
}

/// ROS domain from `ROS_DOMAIN_ID` (0 when unset or empty), as rcl does.
pub fn ros_domain_id() -> Result<u16, NodeError> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(_) => Ok(0),
        Ok(value) if value.trim().is_empty() => Ok(0),
        Ok(value) => match value.trim().parse::<u16>() {
            Ok(id) if id <= 232 => Ok(id),
            _ => Err(NodeError::BadDomainId { value }),
        },
    }
}

/// Sensor-data QoS (REP-2003 / rclcpp `SensorDataQoS`, depth 5): best effort, volatile,
/// keep last 5 — a late depth frame is worth less than the next one.
pub fn sensor_data_qos() -> QosProfile {
    QosProfile::subscription_default().reliability_best_effort().durability(Durability::Volatile).history(History::KeepLast { depth: 5 })
}

/// Reliable QoS for large outputs a subscriber only wants the newest of (the patch map's markers, the
/// birds-eye cloud: up to 1.5 MB each at 30 Hz): as [`reliable_qos`] but the writer keeps the last 2
/// for repair instead of 10. Compatible with every subscriber (depth is not matched).
pub fn latest_reliable_qos() -> QosProfile {
    reliable_qos().history(History::KeepLast { depth: 2 })
}

/// Reliable QoS for outputs (PatchArray, markers, status, joint states): reliable, volatile, keep last 10
/// (the ROS 2 default profile). A full send window drops after 100 ms instead of stalling the loop.
pub fn reliable_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

/// Requests (and replies) a service endpoint holds before the loop takes them.
pub const SERVICE_QUEUE_DEPTH: usize = 1024;

/// Service QoS: reliable, volatile, keep last [`SERVICE_QUEUE_DEPTH`]. rmw's `services_default`
/// keeps 10, which drops requests of an unpaced burst that arrive between two loop passes (a
/// burst of 100 calls had 20-32 answered); the deeper queue holds a burst of 1,000 calls, and a
/// reliable writer still blocks (not drops) beyond it.
pub fn service_qos() -> QosProfile {
    reliable_qos().history(History::KeepLast { depth: SERVICE_QUEUE_DEPTH })
}

/// Split an absolute or relative ROS name (`/camera/depth/image_raw`) into a `ros2_client::Name`.
pub fn ros_name(full: &str) -> Result<Name, NodeError> {
    let bad = |reason: String| NodeError::BadName { name: full.to_string(), reason };
    let (namespace, base) = match full.rsplit_once('/') {
        Some(("", base)) => ("/", base),
        Some((namespace, base)) => (namespace, base),
        None => ("", full),
    };
    Name::new(namespace, base).map_err(|e| bad(format!("{e:?}")))
}

/// A ROS 2 node with its context and the spinner thread (graph, parameter services, rosout).
/// Dropping it stops the spinner and leaves the graph cleanly.
pub struct RosNode {
    // Dropped explicitly in `Drop` (which stops the spinner) before the spinner thread is joined; the
    // context goes last. Always `Some` until then.
    node: Option<Node>,
    spinner: Option<JoinHandle<()>>,
    context: Context,
    network: DdsNetwork,
    names: NodeNames,
    default_name: String,
    /// Publishes the log lines on `/rosout`; stopped before the node goes.
    rosout: Option<crate::rosout::RosoutForwarder>,
}

impl RosNode {
    /// Create the DDS participant on `ROS_DOMAIN_ID` (restricted to 127.0.0.1 for `Loopback`) and the
    /// node `/name`, and start its spinner on a thread (with ros2-client's parameter services).
    pub fn new(name: &str, network: DdsNetwork) -> Result<RosNode, NodeError> {
        RosNode::create(name, NodeNames::plain(name)?, network, true)
    }

    /// The node `default_name` under its ROS arguments (`names`: namespace, name, remaps). Its
    /// parameter services are the node's own ([`crate::param_server::ParameterServer`]).
    pub fn with_names(default_name: &str, names: NodeNames, network: DdsNetwork) -> Result<RosNode, NodeError> {
        RosNode::create(default_name, names, network, false)
    }

    fn create(default_name: &str, names: NodeNames, network: DdsNetwork, builtin_parameters: bool) -> Result<RosNode, NodeError> {
        let name = names.name().to_string();
        let name = name.as_str();
        let domain_id = ros_domain_id()?;
        let mut builder = DomainParticipantBuilder::new(domain_id);
        if network == DdsNetwork::Loopback {
            builder = builder.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]);
        }
        let security = crate::security::resolve(&crate::security::SecuritySettings::from_env(), names.enclave())?;
        match &security {
            crate::security::Security::Off => {}
            crate::security::Security::Permissive { reason } => {
                tracing::warn!("DDS Security asked for but not used (ROS_SECURITY_STRATEGY is not Enforce): {reason}")
            }
            crate::security::Security::On { enclave, dir } => tracing::info!(enclave, dir = %dir.display(), "DDS Security on"),
        }
        if let Some(files) = security.config_files() {
            builder = builder.builtin_security(files);
        }
        let participant = builder.build().map_err(|e| NodeError::Participant { domain_id, reason: format!("{e:?}") })?;
        let context =
            Context::from_domain_participant(participant).map_err(|e| NodeError::Participant { domain_id, reason: format!("{e:?}") })?;
        let node_err = |e: String| NodeError::Node { name: name.to_string(), reason: e };
        let node_name = NodeName::new(names.namespace(), name).map_err(|e| node_err(format!("{e:?}")))?;
        let options = NodeOptions::new().enable_rosout(true).start_parameter_services(builtin_parameters);
        let mut node = context.new_node(node_name, options).map_err(|e| node_err(format!("{e:?}")))?;
        let spinner = node.spinner().map_err(|e| node_err(format!("{e:?}")))?;
        let spinner = std::thread::Builder::new()
            .name(format!("{name}-spinner"))
            .spawn(move || {
                if let Err(e) = futures::executor::block_on(spinner.spin()) {
                    tracing::error!("ROS 2 spinner stopped: {e:?}");
                }
            })
            .map_err(|e| node_err(format!("cannot start the spinner thread: {e}")))?;
        tracing::info!(node = %names.fully_qualified(), domain_id, ?network, "ROS 2 node up");
        let mut ros = RosNode {
            node: Some(node),
            spinner: Some(spinner),
            context,
            network,
            names,
            default_name: default_name.to_string(),
            rosout: None,
        };
        ros.start_rosout()?;
        Ok(ros)
    }

    /// Forward the log lines to `/rosout` (rcl's topic and QoS), named by the node.
    fn start_rosout(&mut self) -> Result<(), NodeError> {
        let publisher =
            self.publisher::<patchwalk_msgs::rcl_interfaces::msg::Log>(crate::rosout::ROSOUT_TOPIC, crate::rosout::rosout_qos())?;
        let logger = self.names.fully_qualified().trim_start_matches('/').replace('/', ".");
        let forwarder = crate::rosout::RosoutForwarder::start(logger, crate::rosout::take_queue(), move |msg| {
            // A failed write is not logged: that line would come back here.
            let _ = publisher.publish(msg);
        })
        .map_err(|e| NodeError::Endpoint {
            what: "publisher",
            name: crate::rosout::ROSOUT_TOPIC.into(),
            reason: e.to_string(),
        })?;
        self.rosout = Some(forwarder);
        Ok(())
    }

    /// The node's name, namespace and remaps.
    pub fn names(&self) -> &NodeNames {
        &self.names
    }

    /// The name the node uses for `name` (`/abs`, `relative`, `~/private`), remaps applied.
    pub fn resolve(&self, name: &str) -> Result<Name, NodeError> {
        ros_name(&self.names.resolve(name)?)
    }

    /// [`RosNode::resolve`] as the fully qualified text (for logs).
    pub fn resolve_text(&self, name: &str) -> Result<String, NodeError> {
        self.names.resolve(name)
    }

    /// A root-namespace name of this node with its default name (`/step_executor/stop`, as the
    /// README's table lists it) made relative to the node (`~/stop`; `/joint_states` ->
    /// `joint_states`), so that it follows `__ns` and `__node`.
    pub fn relative(&self, root_name: &str) -> String {
        crate::names::relative_to_node(&self.default_name, root_name)
    }

    pub fn domain_id(&self) -> u16 {
        self.context.domain_id()
    }

    pub fn network(&self) -> DdsNetwork {
        self.network
    }

    fn node(&mut self, endpoint: &str) -> Result<&mut Node, NodeError> {
        self.node.as_mut().ok_or_else(|| NodeError::Endpoint {
            what: "endpoint",
            name: endpoint.to_string(),
            reason: "the node is shutting down".to_string(),
        })
    }

    /// Typed publisher on `topic`.
    pub fn publisher<M: RosMessage>(&mut self, topic: &str, qos: QosProfile) -> Result<Publisher<M>, NodeError> {
        let err = |e: String| NodeError::Endpoint { what: "publisher", name: topic.to_string(), reason: e };
        let name = self.resolve(topic)?;
        let node = self.node(topic)?;
        let dds_topic = node.create_topic(&name, M::type_name(), &qos).map_err(|e| err(format!("{e:?}")))?;
        node.create_publisher::<M>(&dds_topic, Some(qos)).map_err(|e| err(format!("{e:?}")))
    }

    /// A publisher of `rcl_interfaces/ParameterEvent` on `/parameter_events` (rcl's topic and QoS).
    pub fn parameter_events_publisher(&mut self) -> Result<Publisher<ros2_client::parameters::raw::ParameterEvent>, NodeError> {
        let topic = self.context.get_parameter_events_topic();
        self.node(crate::param_server::PARAMETER_EVENTS_TOPIC)?.create_publisher(&topic, None).map_err(|e| NodeError::Endpoint {
            what: "publisher",
            name: crate::param_server::PARAMETER_EVENTS_TOPIC.to_string(),
            reason: format!("{e:?}"),
        })
    }

    /// Typed subscription on `topic`.
    pub fn subscription<M: RosMessage>(&mut self, topic: &str, qos: QosProfile) -> Result<Subscription<M>, NodeError> {
        let err = |e: String| NodeError::Endpoint { what: "subscription", name: topic.to_string(), reason: e };
        let name = self.resolve(topic)?;
        let node = self.node(topic)?;
        let dds_topic = node.create_topic(&name, M::type_name(), &qos).map_err(|e| err(format!("{e:?}")))?;
        node.create_subscription::<M>(&dds_topic, Some(qos)).map_err(|e| err(format!("{e:?}")))
    }

    /// Typed service server `name` (ServiceMapping::Enhanced, the mapping rmw_fastrtps/cyclonedds use).
    pub fn server<S: RosService>(&mut self, name: &str) -> Result<Server<S::Request, S::Response>, NodeError> {
        self.server_of_type::<S::Request, S::Response>(name, &S::type_name())
    }

    /// Service server `name` of a service type given by name (the rcl_interfaces services).
    pub fn server_of_type<Req, Resp>(&mut self, name: &str, type_name: &ServiceTypeName) -> Result<Server<Req, Resp>, NodeError>
    where
        Req: ros2_client::Message + Clone + 'static,
        Resp: ros2_client::Message + 'static,
    {
        let service_name = self.resolve(name)?;
        self.node(name)?
            .create_server::<Req, Resp>(ServiceMapping::Enhanced, &service_name, type_name, service_qos(), service_qos())
            .map_err(|e| NodeError::Endpoint { what: "service", name: name.to_string(), reason: format!("{e:?}") })
    }

    /// Typed service client of `name` (ServiceMapping::Enhanced, as [`RosNode::server`]).
    pub fn client<S: RosService>(&mut self, name: &str) -> Result<ros2_client::Client<S::Request, S::Response>, NodeError> {
        let service_name = ros_name(name)?;
        self.node(name)?
            .create_client::<S::Request, S::Response>(
                ServiceMapping::Enhanced,
                &service_name,
                &S::type_name(),
                service_qos(),
                service_qos(),
            )
            .map_err(|e| NodeError::Endpoint { what: "client", name: name.to_string(), reason: format!("{e:?}") })
    }

    /// Escape hatch for what this wrapper does not cover (clients, actions, graph queries).
    pub fn node_mut(&mut self) -> Option<&mut Node> {
        self.node.as_mut()
    }
}

impl Drop for RosNode {
    fn drop(&mut self) {
        // Dropping the node tells the spinner to stop; then wait for it so the participant leaves the
        // graph cleanly when the context is dropped.
        drop(self.rosout.take());
        drop(self.node.take());
        if let Some(handle) = self.spinner.take() {
            if handle.join().is_err() {
                tracing::error!("ROS 2 spinner thread panicked");
            }
        }
    }
}

/// Take up to `max` pending messages from `sub` and hand each to `handle`. Undecodable samples are
/// logged (rate-limited through `log`) and skipped; returns how many messages were handled.
pub fn drain<M>(sub: &Subscription<M>, topic: &str, max: usize, log: &mut RateLimitedLog, mut handle: impl FnMut(M, MessageInfo)) -> usize
where
    M: serde::de::DeserializeOwned + 'static,
{
    let mut handled = 0;
    for _ in 0..max {
        match sub.take() {
            Ok(Some((msg, info))) => {
                handle(msg, info);
                handled += 1;
            }
            Ok(None) => break,
            Err(e) => {
                log.warn(topic, format_args!("{topic}: cannot read a sample: {e:?}"));
            }
        }
    }
    handled
}

/// Up to `max` pending requests of `server`, to be answered later with [`respond`] (work that runs
/// off the loop). A failed receive is logged.
pub fn take_requests<Req, Resp>(server: &Server<Req, Resp>, name: &str, max: usize, log: &mut RateLimitedLog) -> Vec<(RmwRequestId, Req)>
where
    Req: ros2_client::Message + Clone + 'static,
    Resp: ros2_client::Message + 'static,
{
    let mut taken = Vec::new();
    for _ in 0..max {
        match server.receive_request() {
            Ok(Some(request)) => taken.push(request),
            Ok(None) => break,
            Err(e) => {
                log.warn(name, format_args!("{name}: cannot read a request: {e:?}"));
            }
        }
    }
    taken
}

/// Answer a request taken with [`take_requests`]; a failed send is logged.
pub fn respond<Req, Resp>(server: &Server<Req, Resp>, name: &str, request_id: RmwRequestId, response: Resp, log: &mut RateLimitedLog)
where
    Req: ros2_client::Message + Clone + 'static,
    Resp: ros2_client::Message + 'static,
{
    if let Err(e) = server.send_response(request_id, response) {
        log.warn(name, format_args!("{name}: cannot send the response: {e:?}"));
    }
}

/// Answer every pending request of `server` with `handle`; a failed receive or send is logged, never
/// fatal. Returns how many requests were answered.
pub fn serve<Req, Resp>(server: &Server<Req, Resp>, name: &str, log: &mut RateLimitedLog, mut handle: impl FnMut(Req) -> Resp) -> usize
where
    Req: ros2_client::Message + Clone + 'static,
    Resp: ros2_client::Message + 'static,
{
    let mut answered = 0;
    // Bounded so a flood of requests cannot starve the rest of the loop.
    for _ in 0..64 {
        match server.receive_request() {
            Ok(Some((request_id, request))) => {
                let response = handle(request);
                match server.send_response(request_id, response) {
                    Ok(()) => answered += 1,
                    Err(e) => {
                        log.warn(name, format_args!("{name}: cannot send the response: {e:?}"));
                    }
                }
            }
            Ok(None) => break,
            Err(e) => {
                log.warn(name, format_args!("{name}: cannot read a request: {e:?}"));
            }
        }
    }
    answered
}

/// Publish, logging (rate-limited) instead of failing when the middleware refuses.
pub fn publish<M: serde::Serialize>(publisher: &Publisher<M>, topic: &str, msg: M, log: &mut RateLimitedLog) {
    if let Err(e) = publisher.publish(msg) {
        let reason = match e {
            ros2_client::WriteError::WouldBlock { .. } => "send window full (reader too slow)".to_string(),
            ros2_client::WriteError::Serialization { reason, .. } => format!("serialization failed: {reason}"),
            ros2_client::WriteError::Io(io) => format!("I/O error: {io}"),
            ros2_client::WriteError::Internal { reason } => reason,
            _ => "middleware error".to_string(),
        };
        log.warn(topic, format_args!("{topic}: cannot publish: {reason}"));
    }
}

/// Wall-clock stamp as `builtin_interfaces/Time`. Node outputs are stamped from their inputs or from
/// [`crate::clock::NodeClock::now`], which follows `/clock` under `use_sim_time`.
pub fn now_stamp() -> Time {
    crate::clock::NodeClock::wall().now()
}

/// Set by SIGINT or SIGTERM; a second signal while shutting down exits at once (code 1).
#[derive(Clone)]
pub struct Shutdown {
    flag: Arc<AtomicBool>,
}

impl Shutdown {
    pub fn install() -> Result<Shutdown, NodeError> {
        let flag = Arc::new(AtomicBool::new(false));
        for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            // Order matters: the conditional exit sees the flag set by the first signal only.
            signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&flag))?;
            signal_hook::flag::register(signal, Arc::clone(&flag))?;
        }
        Ok(Shutdown { flag })
    }

    pub fn requested(&self) -> bool {
        self.flag.load(Ordering::Relaxed)
    }

    /// Request shutdown from inside the program.
    pub fn request(&self) {
        self.flag.store(true, Ordering::Relaxed);
    }
}

/// Default `tracing` filter: RustDDS warns about every loopback-only locator decision and fails to
/// leave multicast groups it never joined on `lo`; both are expected here, so it logs errors only.
pub const DEFAULT_LOG_FILTER: &str = "info,rustdds=error,rustdds::network::udp_listener=off,ros2_client=error";

/// Logs to stderr through `tracing`; `RUST_LOG` overrides the default filter. The `log` records of
/// ros2-client and RustDDS are forwarded (filtered by [`DEFAULT_LOG_FILTER`]).
pub fn init_tracing() {
    init_tracing_with(&[]);
}

/// For a node that runs for hours: free heap pages go back to the system every
/// [`crate::memory::TRIM_PERIOD`] ([`crate::memory`]).
pub fn keep_memory_returnable() {
    if !crate::memory::start_trimming(crate::memory::TRIM_PERIOD) {
        tracing::debug!("no allocator trimming here: resident memory may stay at the high-water mark of the largest messages");
    }
}

/// [`init_tracing`] with the `--ros-args --log-level` directives laid over the filter (over
/// `RUST_LOG` too: the command line is the more specific).
pub fn init_tracing_with(levels: &[LogLevel]) {
    let base = std::env::var("RUST_LOG").ok().filter(|v| !v.trim().is_empty()).unwrap_or_else(|| DEFAULT_LOG_FILTER.to_string());
    let mut directives: Vec<String> = base.split(',').map(str::to_string).collect();
    for level in levels {
        let directive = level.directive();
        if level.logger.is_none() {
            // A global level replaces the default level, not the per-crate quieting.
            directives.retain(|d| d.contains('='));
            directives.insert(0, directive);
        } else {
            directives.push(directive);
        }
    }
    let filter = tracing_subscriber::EnvFilter::try_new(directives.join(","))
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER));
    // Ignore the error of a second initialisation (tests, embedded use).
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    let stderr =
        tracing_subscriber::fmt::layer().with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr())).with_writer(std::io::stderr);
    // The same lines go to /rosout once a node is up (crate::rosout).
    if tracing_subscriber::registry().with(filter).with(stderr).with(crate::rosout::RosoutLayer).try_init().is_ok() {
        crate::rosout::open_early();
    }
}

/// At most one warning per key and period, with the number of suppressed ones (journal-style
/// "one clear log line, rate-limited" for bad input).
pub struct RateLimitedLog {
    period: Duration,
    last: HashMap<String, (Instant, u64)>,
}

impl RateLimitedLog {
    pub fn new(period: Duration) -> RateLimitedLog {
        RateLimitedLog { period, last: HashMap::new() }
    }

    /// Log `message` at warn level unless `key` was logged less than `period` ago. Returns whether it
    /// was logged.
    pub fn warn(&mut self, key: &str, message: std::fmt::Arguments<'_>) -> bool {
        let now = Instant::now();
        match self.last.get_mut(key) {
            Some((at, suppressed)) if now.duration_since(*at) < self.period => {
                *suppressed += 1;
                false
            }
            Some((at, suppressed)) => {
                if *suppressed > 0 {
                    tracing::warn!("{message} ({suppressed} similar suppressed)");
                } else {
                    tracing::warn!("{message}");
                }
                *at = now;
                *suppressed = 0;
                true
            }
            None => {
                tracing::warn!("{message}");
                self.last.insert(key.to_string(), (now, 0));
                true
            }
        }
    }
}

impl Default for RateLimitedLog {
    fn default() -> Self {
        RateLimitedLog::new(Duration::from_secs(2))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_names_split_into_namespace_and_base() {
        let name = ros_name("/camera/depth/image_raw").map(|n| n.to_dds_name("rt", &NodeName::new("/", "x").unwrap(), ""));
        assert_eq!(name.unwrap(), "rt/camera/depth/image_raw");
        let name = ros_name("/joint_states").map(|n| n.to_dds_name("rt", &NodeName::new("/", "x").unwrap(), ""));
        assert_eq!(name.unwrap(), "rt/joint_states");
        let name = ros_name("/step_executor/list_motions").map(|n| n.to_dds_name("rq", &NodeName::new("/", "x").unwrap(), "Request"));
        assert_eq!(name.unwrap(), "rq/step_executor/list_motionsRequest");
    }

    #[test]
    fn rate_limited_log_suppresses_repeats_per_key() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        assert!(log.warn("a", format_args!("first")));
        assert!(!log.warn("a", format_args!("again")));
        assert!(log.warn("b", format_args!("other key")));
        let mut log = RateLimitedLog::new(Duration::ZERO);
        assert!(log.warn("a", format_args!("first")));
        assert!(log.warn("a", format_args!("second")));
    }

    #[test]
    fn qos_presets_are_the_documented_ones() {
        use ros2_client::qos::Reliability;
        assert_eq!(sensor_data_qos().reliability, Reliability::BestEffort);
        assert_eq!(sensor_data_qos().history, History::KeepLast { depth: 5 });
        assert!(matches!(reliable_qos().reliability, Reliability::Reliable { .. }));
        assert_eq!(reliable_qos().history, History::KeepLast { depth: 10 });
        assert_eq!(reliable_qos().durability, Durability::Volatile);
        assert_eq!(service_qos().history, History::KeepLast { depth: SERVICE_QUEUE_DEPTH });
    }

    #[test]
    fn stamps_are_after_2020() {
        assert!(now_stamp().sec > 1_577_836_800);
    }
}

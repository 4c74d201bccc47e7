//! The rcl parameter services of a node (`~/list_parameters`, `~/get_parameters`,
//! `~/get_parameter_types`, `~/describe_parameters`, `~/set_parameters`,
//! `~/set_parameters_atomically`) over its [`Declared`] parameters, answered on a thread of their
//! own so `ros2 param` works whatever the node's loop is doing. An accepted set is handed to the loop
//! as a [`ParameterUpdate`] (the new config and the changed keys), which the loop applies where the
//! keys take effect; the loop's waker is called so it sees it at once. Every declared parameter
//! is announced on `/parameter_events` when the server starts (`new_parameters`), and every accepted
//! set there too (`changed_parameters`), as rclcpp does, so `ros2 param` tools and parameter-event
//! listeners see changes.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mio::{Interest, Poll, Token, Waker};
use ros2_client::parameters::{raw, Parameter, ParameterValue};
use ros2_client::rcl_interfaces as rcl;
use ros2_client::{Publisher, Server, ServiceTypeName};
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::clock::NodeClock;
use crate::declared::Declared;
use crate::node::{self, NodeError, RateLimitedLog, RosNode};

/// The topic of parameter events (rcl's `/parameter_events`).
pub const PARAMETER_EVENTS_TOPIC: &str = "/parameter_events";

/// New parameter values accepted by the parameter services, for the node's loop.
#[derive(Debug, Clone)]
pub struct ParameterUpdate<T> {
    /// The node's config with every change so far.
    pub config: T,
    /// The keys changed since the loop last took an update.
    pub keys: Vec<String>,
    /// When the first of these changes was accepted (for the set -> effect time).
    pub accepted_at: Instant,
}

impl<T> ParameterUpdate<T> {
    /// Whether `key` or a key under it (`prefix.`) changed.
    pub fn changed(&self, prefix: &str) -> bool {
        self.keys.iter().any(|k| k == prefix || k.strip_prefix(prefix).is_some_and(|rest| rest.starts_with('.')))
    }
}

/// The running parameter services; dropping it stops them.
pub struct ParameterServer<T> {
    updates: Receiver<ParameterUpdate<T>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

struct Servers {
    list: Server<rcl::ListParametersRequest, rcl::ListParametersResponse>,
    get: Server<rcl::GetParametersRequest, rcl::GetParametersResponse>,
    types: Server<rcl::GetParameterTypesRequest, rcl::GetParameterTypesResponse>,
    describe: Server<rcl::DescribeParametersRequest, rcl::DescribeParametersResponse>,
    set: Server<rcl::SetParametersRequest, rcl::SetParametersResponse>,
    set_atomically: Server<rcl::SetParametersRequest, rcl::SetParametersAtomicallyResponse>,
}

/// Where parameter events go: the writer, the node's fully qualified name and its clock.
struct Events {
    writer: Publisher<raw::ParameterEvent>,
    node: String,
    clock: NodeClock,
}

impl Events {
    /// Publish `new` and `changed` (name, value) as one event, unless both are empty.
    fn publish<T: Serialize + DeserializeOwned + Clone>(
        &self,
        declared: &Declared<T>,
        new: &[String],
        changed: &[String],
        log: &mut RateLimitedLog,
    ) {
        if new.is_empty() && changed.is_empty() {
            return;
        }
        let params = |names: &[String]| -> Vec<raw::Parameter> {
            names.iter().map(|n| raw::Parameter { name: n.clone(), value: raw::ParameterValue::from(declared.get(n)) }).collect()
        };
        let stamp = self.clock.now();
        let event = raw::ParameterEvent {
            stamp: ros2_client::builtin_interfaces::Time::new(stamp.sec, stamp.nanosec),
            node: self.node.clone(),
            new_parameters: params(new),
            changed_parameters: params(changed),
            deleted_parameters: Vec::new(),
        };
        node::publish(&self.writer, PARAMETER_EVENTS_TOPIC, event, log);
    }
}

impl<T: Serialize + DeserializeOwned + Clone + Send + 'static> ParameterServer<T> {
    /// Offer `declared` on the node's parameter services; `notify` wakes the node's loop on a change;
    /// parameter events are stamped by `clock`.
    pub fn start(
        ros: &mut RosNode,
        declared: Declared<T>,
        notify: Option<Arc<Waker>>,
        clock: NodeClock,
    ) -> Result<ParameterServer<T>, NodeError> {
        let service = |name: &str| ServiceTypeName::new("rcl_interfaces", name);
        let mut servers = Servers {
            list: ros.server_of_type("~/list_parameters", &service("ListParameters"))?,
            get: ros.server_of_type("~/get_parameters", &service("GetParameters"))?,
            types: ros.server_of_type("~/get_parameter_types", &service("GetParameterTypes"))?,
            describe: ros.server_of_type("~/describe_parameters", &service("DescribeParameters"))?,
            set: ros.server_of_type("~/set_parameters", &service("SetParameters"))?,
            set_atomically: ros.server_of_type("~/set_parameters_atomically", &service("SetParametersAtomically"))?,
        };
        let events = Events { writer: ros.parameter_events_publisher()?, node: ros.names().fully_qualified(), clock };
        let poll = Poll::new().map_err(NodeError::Wait)?;
        let registry = poll.registry();
        for result in [
            registry.register(&mut servers.list, Token(0), Interest::READABLE),
            registry.register(&mut servers.get, Token(0), Interest::READABLE),
            registry.register(&mut servers.types, Token(0), Interest::READABLE),
            registry.register(&mut servers.describe, Token(0), Interest::READABLE),
            registry.register(&mut servers.set, Token(0), Interest::READABLE),
            registry.register(&mut servers.set_atomically, Token(0), Interest::READABLE),
        ] {
            result.map_err(NodeError::Wait)?;
        }
        let (tx, updates) = std::sync::mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let stop = Arc::clone(&stop);
            std::thread::Builder::new()
                .name("parameters".into())
                .spawn(move || serve_loop(poll, servers, declared, events, tx, notify, &stop))
                .map_err(|e| NodeError::Node { name: "parameters".into(), reason: format!("cannot start the parameter thread: {e}") })?
        };
        Ok(ParameterServer { updates, stop, thread: Some(thread) })
    }

    /// Every change accepted since the last call, as one update (the latest config, all keys).
    pub fn take_update(&self) -> Option<ParameterUpdate<T>> {
        let mut merged: Option<ParameterUpdate<T>> = None;
        for update in self.updates.try_iter() {
            merged = Some(match merged {
                None => update,
                Some(mut earlier) => {
                    for key in update.keys {
                        if !earlier.keys.contains(&key) {
                            earlier.keys.push(key);
                        }
                    }
                    ParameterUpdate { config: update.config, keys: earlier.keys, accepted_at: earlier.accepted_at }
                }
            });
        }
        merged
    }
}

impl<T> Drop for ParameterServer<T> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            if thread.join().is_err() {
                tracing::error!("the parameter thread panicked");
            }
        }
    }
}

fn serve_loop<T: Serialize + DeserializeOwned + Clone>(
    mut poll: Poll,
    servers: Servers,
    mut declared: Declared<T>,
    parameter_events: Events,
    updates: Sender<ParameterUpdate<T>>,
    notify: Option<Arc<Waker>>,
    stop: &AtomicBool,
) {
    let mut events = mio::Events::with_capacity(16);
    let mut log = RateLimitedLog::default();
    let all: Vec<String> = declared.names().map(str::to_string).collect();
    parameter_events.publish(&declared, &all, &[], &mut log);
    while !stop.load(Ordering::Relaxed) {
        // Readiness is reported once per arrival: every pass drains every server.
        let _ = poll.poll(&mut events, Some(Duration::from_millis(100)));
        node::serve(&servers.list, "list_parameters", &mut log, |req| {
            let (names, prefixes) = declared.list(&req.prefixes, req.depth);
            rcl::ListParametersResponse { result: rcl::ListParametersResult { names, prefixes } }
        });
        node::serve(&servers.get, "get_parameters", &mut log, |req| rcl::GetParametersResponse {
            values: req.names.iter().map(|n| raw::ParameterValue::from(declared.get(n))).collect(),
        });
        node::serve(&servers.types, "get_parameter_types", &mut log, |req| rcl::GetParameterTypesResponse {
            values: req.names.iter().map(|n| ParameterValue::to_parameter_type_raw(&declared.get(n))).collect(),
        });
        node::serve(&servers.describe, "describe_parameters", &mut log, |req| rcl::DescribeParametersResponse {
            values: req.names.iter().map(|n| raw::ParameterDescriptor::from(declared.describe(n))).collect(),
        });
        let mut changed: Vec<String> = Vec::new();
        node::serve(&servers.set, "set_parameters", &mut log, |req| {
            let results = req
                .parameter
                .into_iter()
                .map(|p| {
                    let Parameter { name, value } = Parameter::from(p);
                    let result = apply(&mut declared, &[(name, value)], &updates).map(|keys| changed.extend(keys));
                    raw::SetParametersResult::from(result)
                })
                .collect();
            rcl::SetParametersResponse { results }
        });
        node::serve(&servers.set_atomically, "set_parameters_atomically", &mut log, |req| {
            let params: Vec<(String, ParameterValue)> =
                req.parameter.into_iter().map(Parameter::from).map(|Parameter { name, value }| (name, value)).collect();
            let result = apply(&mut declared, &params, &updates).map(|keys| changed.extend(keys));
            rcl::SetParametersAtomicallyResponse { result: raw::SetParametersResult::from(result) }
        });
        if !changed.is_empty() {
            changed.dedup();
            parameter_events.publish(&declared, &[], &changed, &mut log);
            if let Some(waker) = &notify {
                let _ = waker.wake();
            }
        }
    }
}

fn apply<T: Serialize + DeserializeOwned + Clone>(
    declared: &mut Declared<T>,
    params: &[(String, ParameterValue)],
    updates: &Sender<ParameterUpdate<T>>,
) -> Result<Vec<String>, String> {
    let accepted_at = Instant::now();
    match declared.set(params) {
        Ok(change) => {
            tracing::info!("parameter set: {}", params.iter().map(|(n, v)| format!("{n} = {v:?}")).collect::<Vec<_>>().join(", "));
            let keys = change.keys.clone();
            // The loop is gone only while the node shuts down.
            let _ = updates.send(ParameterUpdate { config: change.config, keys: change.keys, accepted_at });
            Ok(keys)
        }
        Err(reason) => {
            tracing::warn!("parameter set refused: {reason}");
            Err(reason)
        }
    }
}

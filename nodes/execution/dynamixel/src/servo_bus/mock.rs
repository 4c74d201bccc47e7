//! In-memory servo chain for fast, deterministic unit tests of the player: every servo keeps goal,
//! present position, torque and hardware-error state; present position moves toward the goal by at
//! most `max_step_ticks` per sync read (one control cycle). Faults (silent servo, hardware error)
//! are injected through the shared [`MockState`], and every sync write is logged.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};

use super::{BusError, ServoBus, SyncReadData, SyncReadResult};
use crate::mx28;

/// One simulated servo.
#[derive(Debug, Clone, PartialEq)]
pub struct MockServo {
    pub goal: i32,
    pub present: i32,
    pub torque: bool,
    pub hardware_error: u8,
    pub silent: bool,
}

/// Shared state of the mock chain (inspect / inject from tests).
#[derive(Debug, Default)]
pub struct MockState {
    pub servos: BTreeMap<u8, MockServo>,
    /// Goal-position sync writes in order: (servo, ticks) per write.
    pub goal_writes: Vec<Vec<(u8, i32)>>,
    /// Number of sync reads served.
    pub sync_reads: usize,
    /// Max movement per sync read (ticks); 0 = jump to goal.
    pub max_step_ticks: i32,
    /// Servos rebooted, in order.
    pub reboots: Vec<u8>,
    /// Number of reconnects asked for.
    pub reconnects: usize,
}

/// Handle implementing [`ServoBus`]; clones share the state.
#[derive(Debug, Clone)]
pub struct MockBus {
    state: Arc<Mutex<MockState>>,
}

impl MockBus {
    /// Servos `ids` at the centre position, torque off.
    pub fn new(ids: &[u8]) -> Self {
        let servos =
            ids.iter().map(|&id| (id, MockServo { goal: 2048, present: 2048, torque: false, hardware_error: 0, silent: false })).collect();
        Self { state: Arc::new(Mutex::new(MockState { servos, ..Default::default() })) }
    }

    /// Lock the shared state (a poisoned lock is recovered: the state is plain data).
    pub fn state(&self) -> MutexGuard<'_, MockState> {
        self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

fn table_value(servo: &MockServo, address: u16) -> Option<i64> {
    Some(match address {
        mx28::MODEL_NUMBER_ADDR => i64::from(mx28::MODEL_NUMBER),
        mx28::TORQUE_ENABLE => i64::from(servo.torque),
        mx28::HARDWARE_ERROR_STATUS => i64::from(servo.hardware_error),
        mx28::GOAL_POSITION => i64::from(servo.goal),
        mx28::PRESENT_POSITION => i64::from(servo.present),
        // Present Input Voltage (12.0 V) followed by Present Temperature (32 °C).
        mx28::PRESENT_INPUT_VOLTAGE => 120 | (32 << 16),
        _ => return None,
    })
}

impl ServoBus for MockBus {
    fn ping(&mut self, id: u8) -> Result<u16, BusError> {
        let state = self.state();
        match state.servos.get(&id) {
            Some(servo) if !servo.silent => Ok(mx28::MODEL_NUMBER),
            _ => Err(BusError::Timeout { id }),
        }
    }

    fn read(&mut self, id: u8, address: u16, count: u16) -> Result<Vec<u8>, BusError> {
        let state = self.state();
        let servo = state.servos.get(&id).filter(|s| !s.silent).ok_or(BusError::Timeout { id })?;
        let value = table_value(servo, address).ok_or(BusError::Status { id, code: 0x07 })?;
        Ok(value.to_le_bytes().into_iter().take(usize::from(count)).collect())
    }

    fn write(&mut self, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
        let mut state = self.state();
        let servo = state.servos.get_mut(&id).filter(|s| !s.silent).ok_or(BusError::Timeout { id })?;
        apply_write(servo, id, address, data)
    }

    fn sync_write(&mut self, address: u16, count: u16, data: &[(u8, Vec<u8>)]) -> Result<(), BusError> {
        let mut state = self.state();
        let mut logged = Vec::new();
        for (id, bytes) in data {
            if bytes.len() != usize::from(count) {
                return Err(BusError::InvalidRequest(format!("servo {id}: {} bytes for a {count}-byte sync write", bytes.len())));
            }
            if let Some(servo) = state.servos.get_mut(id).filter(|s| !s.silent) {
                // Sync write has no status packet: errors are invisible to the master, as on a real bus.
                let _ = apply_write(servo, *id, address, bytes);
                if address == mx28::GOAL_POSITION {
                    logged.push((*id, servo.goal));
                }
            }
        }
        if address == mx28::GOAL_POSITION {
            state.goal_writes.push(logged);
        }
        Ok(())
    }

    fn sync_read(&mut self, ids: &[u8], address: u16, count: u16) -> Result<Vec<SyncReadResult>, BusError> {
        let mut state = self.state();
        state.sync_reads += 1;
        let step = state.max_step_ticks;
        for servo in state.servos.values_mut() {
            if servo.torque && servo.hardware_error == 0 {
                let delta = servo.goal - servo.present;
                servo.present += if step > 0 { delta.clamp(-step, step) } else { delta };
            }
        }
        Ok(ids
            .iter()
            .map(|&id| {
                let result = match state.servos.get(&id).filter(|s| !s.silent) {
                    None => Err(BusError::Timeout { id }),
                    Some(servo) => table_value(servo, address)
                        .map(|v| SyncReadData {
                            data: v.to_le_bytes().into_iter().take(usize::from(count)).collect(),
                            alert: servo.hardware_error != 0,
                        })
                        .ok_or(BusError::Status { id, code: 0x07 }),
                };
                (id, result)
            })
            .collect())
    }

    fn reboot(&mut self, id: u8) -> Result<(), BusError> {
        let mut state = self.state();
        let servo = state.servos.get_mut(&id).filter(|s| !s.silent).ok_or(BusError::Timeout { id })?;
        servo.hardware_error = 0;
        servo.torque = false;
        servo.goal = servo.present;
        state.reboots.push(id);
        Ok(())
    }

    fn reconnect(&mut self) -> Result<(), BusError> {
        self.state().reconnects += 1;
        Ok(())
    }
}

fn apply_write(servo: &mut MockServo, id: u8, address: u16, data: &[u8]) -> Result<(), BusError> {
    match (address, data) {
        (mx28::TORQUE_ENABLE, [value]) => {
            servo.torque = *value != 0;
            if servo.torque {
                servo.goal = servo.present;
            }
            Ok(())
        }
        (mx28::GOAL_POSITION, [a, b, c, d]) => {
            let goal = i32::from_le_bytes([*a, *b, *c, *d]);
            if !(0..=4095).contains(&goal) {
                return Err(BusError::Status { id, code: 0x06 });
            }
            if servo.torque {
                servo.goal = goal;
            }
            Ok(())
        }
        (mx28::RETURN_DELAY_TIME, [_]) if !servo.torque => Ok(()),
        _ => Err(BusError::Status { id, code: 0x07 }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moves_toward_goal_only_with_torque() {
        let mut bus = MockBus::new(&[1, 2]);
        bus.state().max_step_ticks = 100;
        super::super::sync_write_u32(&mut bus, mx28::GOAL_POSITION, &[(1, 2500), (2, 2500)]).unwrap();
        assert_eq!(bus.state().servos[&1].goal, 2048, "no torque: goal ignored");
        bus.write(1, mx28::TORQUE_ENABLE, &[1]).unwrap();
        super::super::sync_write_u32(&mut bus, mx28::GOAL_POSITION, &[(1, 2500), (2, 2500)]).unwrap();
        let positions = super::super::read_present_positions(&mut bus, &[1, 2]).unwrap();
        assert_eq!(positions, vec![2148, 2048]);
    }

    #[test]
    fn faults_become_typed_errors() {
        let mut bus = MockBus::new(&[1, 2, 3]);
        bus.state().servos.get_mut(&2).unwrap().silent = true;
        let (err, partial) = super::super::read_present_positions(&mut bus, &[1, 2, 3]).unwrap_err();
        assert_eq!(err, BusError::Timeout { id: 2 });
        assert_eq!(partial, vec![Some(2048), None, Some(2048)]);
        bus.state().servos.get_mut(&2).unwrap().silent = false;
        bus.state().servos.get_mut(&3).unwrap().hardware_error = mx28::HW_OVERLOAD;
        let (err, _) = super::super::read_present_positions(&mut bus, &[1, 2, 3]).unwrap_err();
        assert_eq!(err, BusError::Hardware { id: 3, bits: mx28::HW_OVERLOAD });
        assert!(err.to_string().contains("overload"));
    }
}

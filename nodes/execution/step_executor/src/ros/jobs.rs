//! Work of the step_executor's services that takes long (a training fit on the mapper's cloud, a
//! library save or delete with fsync) runs on one worker thread, in arrival order, so the node's
//! loop keeps answering e-stops and publishing status meanwhile. Each finished job comes back
//! through [`Jobs::finished`] and wakes the loop; the loop then answers the request that started it.

use std::sync::Arc;
use std::thread::JoinHandle;

use crossbeam_channel::{Receiver, Sender};
use patchwalk_msgs::sensor_msgs::msg::PointCloud2;
use patchwalk_spl::patch::Patch;
use ros2_client::service::RmwRequestId;
use step_executor::library::LibraryError;
use step_executor::runtime::{FitError, FitJob, LibraryChange};

use super::convert;

/// What the worker is asked to do.
pub enum Job {
    /// `select_target` MODE_FIT_AT_POINT: decode the cloud, fit around the point.
    Fit { request_id: RmwRequestId, job: FitJob, cloud: Arc<PointCloud2> },
    /// `save_motion` or `delete_motion`: write the prepared library.
    Write { request_id: RmwRequestId, save: bool, name: String, change: LibraryChange },
}

/// A finished job, to be answered by the loop.
pub enum Finished {
    Fit { request_id: RmwRequestId, result: Result<Patch, FitError> },
    Write { request_id: RmwRequestId, save: bool, name: String, change: LibraryChange, result: Result<(), LibraryError> },
}

/// The worker thread is gone (it ends only when the node shuts down or a job panicked).
#[derive(Debug, thiserror::Error)]
#[error("the job worker has stopped")]
pub struct WorkerStopped;

/// The worker thread and its channels.
pub struct Jobs {
    submit: Option<Sender<Job>>,
    finished: Receiver<Finished>,
    thread: Option<JoinHandle<()>>,
}

impl Jobs {
    /// Start the worker; `wake` is called after each finished job.
    pub fn spawn(wake: impl Fn() + Send + 'static) -> std::io::Result<Self> {
        let (submit, jobs) = crossbeam_channel::unbounded::<Job>();
        let (done, finished) = crossbeam_channel::unbounded::<Finished>();
        let thread = std::thread::Builder::new().name("executor-jobs".into()).spawn(move || {
            // Created by the (possibly real-time) ROS loop: fits and writes are long and must not
            // preempt it or the bus thread.
            if !patchwalk_dynamixel::priority::make_normal() {
                tracing::warn!("executor jobs: could not return to normal scheduling");
            }
            for job in jobs {
                let result = match job {
                    Job::Fit { request_id, job, cloud } => {
                        let result = convert::points_from_cloud(&cloud).map_err(FitError::BadCloud).and_then(|points| job.run(&points));
                        Finished::Fit { request_id, result }
                    }
                    Job::Write { request_id, save, name, change } => {
                        let result = change.write();
                        Finished::Write { request_id, save, name, change, result }
                    }
                };
                if done.send(result).is_err() {
                    break;
                }
                wake();
            }
        })?;
        Ok(Self { submit: Some(submit), finished, thread: Some(thread) })
    }

    /// Queue a job (it runs after the ones before it).
    pub fn submit(&self, job: Job) -> Result<(), WorkerStopped> {
        self.submit.as_ref().ok_or(WorkerStopped)?.send(job).map_err(|_| WorkerStopped)
    }

    /// Jobs finished since the last call.
    pub fn finished(&self) -> impl Iterator<Item = Finished> + '_ {
        self.finished.try_iter()
    }
}

impl Drop for Jobs {
    /// Finish the queued jobs (a save in progress is completed, never cut), then stop.
    fn drop(&mut self) {
        self.submit.take();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

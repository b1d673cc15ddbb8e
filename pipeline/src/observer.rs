//! Where a pipeline reports to, shared by [`crate::demo`] and [`crate::bringup`].

use tcsense_train::Progress;

/// Where a running pipeline (the demo, the bring-up) reports to: the binary prints lines and
/// draws progress bars, the Python module writes lines to stderr. Called from the thread that runs the demo.
pub trait Observer: Sync {
    /// One line of the demo's log (steps, plans, files written, timings).
    fn line(&self, text: &str);
    /// Progress of a long step: `done` of `of` items of `what` (dataset scenes, evaluated
    /// frames); `done == of` ends it.
    fn items(&self, _what: &str, _done: usize, _of: usize) {}
    /// Where a training reports its steps and epochs.
    fn training(&self) -> &dyn Progress;
}

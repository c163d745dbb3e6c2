//! Measures of generated driving scenes (paper §4, the authors' definitions where they exist):
//! [`mmd`] of agent attribute groups between generated and real scenes, the BEV [`collision`] rate, and
//! [`l2`] position errors of ego and agents against ground truth, next to the constant-velocity baseline;
//! how far [`kinematics`] alone predicts a dataset's agents, which bounds what beating that baseline can
//! mean on it; and how a model uses the kinematic [`hint`] it is given. Over a rollout's [`horizon`], the
//! same statistics for generated and real scenes: agents per frame, entries and exits, collisions, agents
//! [`offroad`], heading against motion, speed and acceleration, and whether agents brake on their
//! [`approach`] to a standing one; the 95 % intervals of rates taken from [`counts`] of events. Each
//! run [`targets`]: the bars the project holds long rollouts to, checked against what was measured.

pub mod approach;
pub mod collision;
pub mod counts;
pub mod hint;
pub mod horizon;
pub mod kinematics;
pub mod l2;
pub mod leaving;
pub mod mmd;
pub mod offroad;
pub mod targets;

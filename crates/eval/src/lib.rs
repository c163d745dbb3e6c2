//! Measures of generated driving scenes (paper §4, the authors' definitions where they exist):
//! [`mmd`] of agent attribute groups between generated and real scenes, the BEV [`collision`] rate, and
//! [`l2`] position errors of ego and agents against ground truth, next to the constant-velocity baseline.

pub mod collision;
pub mod l2;
pub mod mmd;

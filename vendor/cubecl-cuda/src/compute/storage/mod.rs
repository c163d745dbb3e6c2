pub mod cpu;
pub mod gpu;
pub mod remap;

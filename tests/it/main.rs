//! The one integration-test binary (faster to build on two cores): each module tests one room through real parts.

mod analysis;
mod capacity;
mod cli_service;
mod client;
mod compressed;
mod condition;
mod dashboard;
mod device;
mod estimate_stream;
mod estimator;
mod faults;
mod hardening;
mod http;
mod link_faults;
mod loud;
mod mqtt;
mod multi;
mod noload;
mod plant;
mod prometheus;
mod proxy;
mod rtu;
mod service;
mod simulator;
mod soak;
mod support;

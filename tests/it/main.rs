//! The one integration-test binary (faster to build on two cores): each module tests one room through real parts.

mod faults;
mod http;
mod service;
mod support;

//! The commands, by family: one module per command family (a folder where the family is
//! large), each subcommand its own function. A command module uses `crate::shared`, the
//! reports and the library crates, never another command's module.

pub mod bench;
pub mod bus;
pub mod calib;
pub mod calibrate;
pub mod correct;
pub mod demo;
pub mod export;
pub mod import;
pub mod lab;
pub mod proto;
pub mod shape;
pub mod sim;
pub mod view;

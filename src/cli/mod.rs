//! The `cadence` command line: one module per subcommand, each turning its arguments into the
//! library's options, calling the library and printing the result. No engine code lives here.

pub mod decode;
pub mod doctor;
pub mod home;
pub mod print;
pub mod serve;

//! Read PDS3 (ODL) labels and the products they describe. This crate knows file formats and
//! no science: it turns bytes into values and arrays and says precisely what is wrong with
//! a file that does not match its label.

pub mod envi;
mod error;
pub mod lola;
pub mod m3;
pub mod odl;
pub mod raw;
pub mod solar;
pub mod time;

pub use error::{Error, Result};
pub use lola::{read_label, read_label_bytes};
pub use odl::{parse_label, Label, Object, ParseError, Pointer, Value};

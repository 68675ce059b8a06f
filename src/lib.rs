//! sfsfuse: shape-from-shading fusion of lunar imagery with laser altimetry.
//!
//! The map of the code is docs/architecture.md.
pub mod bench;
pub mod cluster;
pub mod demo;
pub mod error;
pub mod export;
pub mod fetch;
pub mod fusion;
pub mod grid;
pub mod ingest;
pub mod inspect;
pub mod output;
pub mod photometry;
pub mod pipeline;
pub mod progress;
pub mod quicklook;
pub mod raster;
pub mod registration;
pub mod rng;
pub mod sanity;
pub mod spectral;
pub mod synth;
pub mod tiling;
pub mod workflow;

pub use error::{Error, Result};

//! sfsfuse: shape-from-shading fusion of lunar imagery with laser altimetry.
//!
//! The map of the code is docs/architecture.md.

/// The build's identity: the crate version and a hash of the sources and `Cargo.lock` it was
/// built from (build.rs), e.g. `0.1.0+src.1f0c…`. Plan, tile and run keys and the products'
/// `SFSFUSE_VERSION` carry it, so that tiles and plans another build left in an output
/// directory are never taken for this one's (the version number alone does not change with
/// every change of the code that computes the products).
pub const BUILD: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    "+src.",
    env!("SFSFUSE_SOURCE_ID")
);
pub mod bench;
pub mod cluster;
pub mod demo;
pub mod ephemeris;
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
pub mod striping;
pub mod synth;
pub mod tiling;
pub mod workflow;

pub use error::{Error, Result};

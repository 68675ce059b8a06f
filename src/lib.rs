//! sfsfuse: shape-from-shading fusion of lunar imagery with laser altimetry.
pub mod fusion;
pub mod photometry;
pub mod rng;
pub mod spectral;
pub mod synth;

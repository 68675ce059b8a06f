//! sfsfuse: shape-from-shading fusion of lunar imagery with laser altimetry.
pub mod photometry;

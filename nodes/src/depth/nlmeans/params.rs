//! The parameters of the three NL-means nodes and their shared core.

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

use super::common::*;

// ---------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of the `NLMeansDepth` node ([`prune_outliers`] then
    /// [`nlmeans_filter`]).
    pub struct NLMeansDepthParams {
        /// Radius of the search window W_i in pixels (eq. 1): candidates come
        /// from a (2r+1) x (2r+1) window, 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 1, max: 30 };
        /// Radius of the compared patches N in pixels (eq. 2): 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter h (eq. 2), in units of the guide feature
        /// sqrt(c / (1 + c)) of each linear channel (in [0, 1)): the weight
        /// is exp(-mean patch distance), the distance of one pixel being the
        /// sum over channels of squared differences / h_color^2.
        pub h_color: f64 = 0.1, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres: depth patch differences
        /// (eq. 5) and the discontinuity factor xi (eq. 3) enter as
        /// (dz / h_depth)^2.
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Prune outliers (prune_outliers) before filtering; pruned pixels
        /// become holes with confidence 0.
        pub prune: bool = true, ParamKind::Bool;
        /// Radius in pixels of the neighbourhood whose predictions model a
        /// pixel's depth in the outlier test.
        pub outlier_radius: usize = 2usize, ParamKind::Int { min: 1, max: 10 };
        /// Prior probability that a measurement is an outlier (weight of the
        /// uniform component of the mixture).
        pub outlier_prior: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 0.999 };
        /// A pixel whose posterior outlier probability exceeds this becomes
        /// a hole. Above 0: the probability of any pixel with a neighbour
        /// is, so 0 would prune them all.
        pub outlier_threshold: f64 = 0.5, ParamKind::Float { min: 1e-6, max: 1.0 };
        /// Constant part of the depth noise standard deviation, metres (the
        /// normal component of the mixture).
        pub noise_sigma_m: f64 = 0.01, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Part of the depth noise standard deviation proportional to depth.
        pub noise_sigma_rel: f64 = 0.01, ParamKind::Float { min: 0.0, max: 10.0 };
    }
}

node_params! {
    /// Parameters of the `NLMeansUpsample` node ([`nlmeans_upsample`]).
    pub struct NLMeansUpsampleParams {
        /// Radius of the search window in high-resolution pixels (eq. 4), at
        /// least: with a spatial falloff (`spatial_sigma` > 0) each step
        /// widens it to twice its factor (rounded up, at most 30), so that a
        /// window holds 4 to 5 low-resolution samples across each axis
        /// wherever the depth has no holes (remaining holes are inpainted,
        /// see `iterations`). 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 1, max: 30 };
        /// Standard deviation, in low-resolution pixels, of a Gaussian falloff
        /// of each weight with the distance between the pixel and the
        /// sample (the spatial term of Kopf et al.'s joint bilateral
        /// upsampling, not in eq. 4): nearer samples count more, so a
        /// patch that resembles the pixel's across an edge, but lies two
        /// samples away, does not outweigh the pixel's own neighbours.
        /// 0 = none: eq. 4 as published, a uniform window of `search_radius`.
        pub spatial_sigma: f64 = 2.0, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Radius of the color patches in high-resolution pixels (the weights
        /// w^(u) of eq. 4): 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Radius of the depth patches in low-resolution pixels (the weights
        /// w(i_low, j_low) of eq. 4, chosen for the depth resolution): 1
        /// gives 3x3.
        pub low_patch_radius: usize = 1usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter (see `NLMeansDepth`), guide feature units.
        pub h_color: f64 = 0.1, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres (see `NLMeansDepth`).
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Linear blend of eq. 4: weight = (1 - alpha) w(i_low, j_low) +
        /// alpha w^(u)(i, j); 0 uses only the low-resolution depth
        /// similarity, 1 only the high-resolution color similarity.
        pub alpha: f64 = 0.9, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Prune outliers (flying pixels, spikes) of the low-resolution depth
        /// first, as the paper does before the transformation.
        pub prune: bool = true, ParamKind::Bool;
        /// Outlier test neighbourhood radius, low-resolution pixels.
        pub outlier_radius: usize = 2usize, ParamKind::Int { min: 1, max: 10 };
        /// Prior probability of an outlier.
        pub outlier_prior: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 0.999 };
        /// Posterior outlier probability above which a sample is dropped.
        pub outlier_threshold: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Constant part of the depth noise standard deviation, metres.
        pub noise_sigma_m: f64 = 0.01, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Part of the depth noise standard deviation proportional to depth.
        pub noise_sigma_rel: f64 = 0.01, ParamKind::Float { min: 0.0, max: 10.0 };
        /// Inpainting iterations (eq. 5) for high-resolution pixels left
        /// without an estimate (holes of the low-resolution depth, windows
        /// without samples); 0 leaves them as holes.
        pub iterations: usize = 16usize, ParamKind::Int { min: 0, max: 10000 };
        /// Largest upsampling factor of one step: a larger factor runs in
        /// equal steps of at most this, each eq. 4 guided by the colour
        /// averaged down to that step's size, so every search window holds
        /// samples at any factor. 0 = one step at the full factor (the
        /// paper's scheme).
        pub max_step_factor: f64 = 4.0, ParamKind::Float { min: 0.0, max: 64.0 };
    }
}

node_params! {
    /// Parameters of the `NLMeansInpaint` node ([`nlmeans_inpaint`]).
    pub struct NLMeansInpaintParams {
        /// Radius of the search window in pixels; each iteration fills the
        /// holes within this distance of known pixels. 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 1, max: 30 };
        /// Radius of the compared patches in pixels: 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter (see `NLMeansDepth`), guide feature
        /// units. Smaller than for filtering: a hole has no depth of its own,
        /// so the color alone must tell which surface it belongs to.
        pub h_color: f64 = 0.05, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres (see `NLMeansDepth`).
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Maximum number of iterations; stops earlier when no hole is left
        /// or an iteration fills nothing.
        pub iterations: usize = 64usize, ParamKind::Int { min: 0, max: 10000 };
        /// Far-depth prior (Sec. 2.3): multiply each weight by
        /// (z_j / z_max)^2, favouring the background, for disocclusions.
        pub far_prior: bool = false, ParamKind::Bool;
        /// Background side: holes beside a depth edge (projector shadows,
        /// flying pixels) are filled from the far side: each weight times
        /// exp(-background * max(0, (z_max - z_j) / z_max - edge_step)),
        /// z_max the largest known depth in the search window. 0 = off (the
        /// paper's eq. 5 exactly).
        pub background: f64 = 50.0, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Relative depth step within the search window beyond which the near
        /// side counts as across an occlusion edge (0.05: 5 % of the depth;
        /// over an 11-pixel window at f = 525 px that is a surface slanted
        /// about 80 degrees).
        pub edge_step: f64 = 0.05, ParamKind::Float { min: 0.001, max: 1.0 };
    }
}

/// Parameters of [`prune_outliers`](crate::depth::nlmeans::prune_outliers) (the outlier fields of the node
/// parameter structs; see [`NLMeansDepthParams::prune_params`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PruneParams {
    /// Neighbourhood radius in pixels (at least 1).
    pub radius: usize,
    /// Prior probability `pi` of an outlier, in `(0, 1)`.
    pub prior: f64,
    /// Posterior outlier probability above which a pixel becomes a hole.
    pub threshold: f64,
    /// Constant part of the noise standard deviation, metres (positive).
    pub sigma_m: f64,
    /// Part of the noise standard deviation proportional to depth.
    pub sigma_rel: f64,
}

impl Default for PruneParams {
    fn default() -> Self {
        NLMeansDepthParams::default().prune_params()
    }
}

impl NLMeansDepthParams {
    /// The outlier-test fields.
    pub fn prune_params(&self) -> PruneParams {
        PruneParams {
            radius: self.outlier_radius,
            prior: self.outlier_prior,
            threshold: self.outlier_threshold,
            sigma_m: self.noise_sigma_m,
            sigma_rel: self.noise_sigma_rel,
        }
    }
}

impl NLMeansUpsampleParams {
    /// The outlier-test fields.
    pub fn prune_params(&self) -> PruneParams {
        PruneParams {
            radius: self.outlier_radius,
            prior: self.outlier_prior,
            threshold: self.outlier_threshold,
            sigma_m: self.noise_sigma_m,
            sigma_rel: self.noise_sigma_rel,
        }
    }
}

impl PruneParams {
    pub(super) fn check(&self) -> Result<(), NodeError> {
        if self.radius == 0 || self.radius > MAX_PATCH_RADIUS {
            return Err(NodeError::param(
                "outlier_radius",
                format!("must be in [1, {MAX_PATCH_RADIUS}]"),
            ));
        }
        if !(self.prior > 0.0 && self.prior < 1.0) {
            return Err(NodeError::param("outlier_prior", "must be in (0, 1)"));
        }
        if self.threshold.is_nan() || self.threshold <= 0.0 {
            return Err(NodeError::param(
                "outlier_threshold",
                "must be above 0 (every pixel with a neighbour has an outlier probability above 0: 0 prunes them all)",
            ));
        }
        if !(self.sigma_m.is_finite() && self.sigma_m > 0.0) {
            return Err(NodeError::param(
                "noise_sigma_m",
                "must be finite and positive",
            ));
        }
        if !(self.sigma_rel.is_finite() && self.sigma_rel >= 0.0) {
            return Err(NodeError::param(
                "noise_sigma_rel",
                "must be finite and non-negative",
            ));
        }
        Ok(())
    }
}

/// The NL-means parameters every pass shares, checked.
#[derive(Debug, Clone, Copy)]
pub(super) struct Core {
    pub(super) search: usize,
    pub(super) patch: usize,
    pub(super) inv_hc2: f64,
    pub(super) inv_hd2: f64,
}

impl Core {
    pub(super) fn new(
        search: usize,
        patch: usize,
        h_color: f64,
        h_depth: f64,
    ) -> Result<Self, NodeError> {
        if search > MAX_SEARCH_RADIUS {
            return Err(NodeError::param(
                "search_radius",
                format!("must be at most {MAX_SEARCH_RADIUS}"),
            ));
        }
        if patch > MAX_PATCH_RADIUS {
            return Err(NodeError::param(
                "patch_radius",
                format!("must be at most {MAX_PATCH_RADIUS}"),
            ));
        }
        // Guards of the divisions below: h > 0 and finite.
        if !(h_color.is_finite() && h_color > 0.0) {
            return Err(NodeError::param("h_color", "must be finite and positive"));
        }
        if !(h_depth.is_finite() && h_depth > 0.0) {
            return Err(NodeError::param("h_depth", "must be finite and positive"));
        }
        let (inv_hc2, inv_hd2) = (1.0 / (h_color * h_color), 1.0 / (h_depth * h_depth));
        // h so small that 1 / h^2 overflows would turn a zero term into NaN
        if !inv_hc2.is_finite() {
            return Err(NodeError::param(
                "h_color",
                "is too small (1 / h^2 overflows)",
            ));
        }
        if !inv_hd2.is_finite() {
            return Err(NodeError::param(
                "h_depth",
                "is too small (1 / h^2 overflows)",
            ));
        }
        Ok(Self {
            search,
            patch,
            inv_hc2,
            inv_hd2,
        })
    }
}

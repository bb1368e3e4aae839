//! The IDArb sampling loop (`IDArbDiffusionPipeline.__call__` with guidance scale 1): encode the
//! views, denoise 3 domain latents per view jointly, decode. One object per call; the batch layout
//! is (view, domain) with the domain fastest.
use super::autoencoder_kl::AutoencoderKL;
use super::scheduling_ddim::DdimScheduler;
use super::unet_dr2d_condition::UNetDR2DConditionModel;
use candle_core::{bail, Result, Tensor};

/// Number of label domains: albedo, normal, metallic+roughness.
pub const NUM_DOMAINS: usize = 3;

pub struct IdarbPipeline {
    pub unet: UNetDR2DConditionModel,
    pub vae: AutoencoderKL,
    /// Prompt embeddings [3, 77, C_text] for 'albedo', 'normal', 'metallic and roughness'.
    pub text_embeddings: Tensor,
}

/// What the sampler reports after each step (the fixture checks every one).
pub struct StepReport<'a> {
    pub step: usize,
    pub timestep: usize,
    pub v_pred: &'a Tensor,
    pub latents: &'a Tensor,
}

impl IdarbPipeline {
    pub fn new(unet: UNetDR2DConditionModel, vae: AutoencoderKL, text_embeddings: Tensor) -> Result<Self> {
        let (d, _, c) = text_embeddings.dims3()?;
        if d < NUM_DOMAINS || c != unet.config.cross_attention_dim {
            bail!("text embeddings {:?} do not fit the UNet (need [≥3, 77, {}])", text_embeddings.dims(), unet.config.cross_attention_dim);
        }
        let text_embeddings = text_embeddings.narrow(0, 0, NUM_DOMAINS)?.to_dtype(candle_core::DType::F32)?;
        Ok(Self { unet, vae, text_embeddings })
    }

    /// Text context for N views: rows `3v + d` get prompt d. [3N, 77, C].
    pub fn context(&self, num_views: usize) -> Result<Tensor> {
        let (d, l, c) = self.text_embeddings.dims3()?;
        self.text_embeddings.unsqueeze(0)?.broadcast_as((num_views, d, l, c))?.contiguous()?.reshape((num_views * d, l, c))
    }

    /// RGB views on white in [0, 1] [N, 3, H, W] → image latents [3N, 4, H/8, W/8] (each view's
    /// scaled latent mean repeated for its 3 domains).
    pub fn encode_images(&self, rgb: &Tensor) -> Result<Tensor> {
        let lat = self.vae.encode_scaled_mean(&rgb.affine(2.0, -1.0)?)?;
        let (n, c, h, w) = lat.dims4()?;
        lat.unsqueeze(1)?.broadcast_as((n, NUM_DOMAINS, c, h, w))?.contiguous()?.reshape((n * NUM_DOMAINS, c, h, w))
    }

    /// One v-prediction: `latents` [3N, 4, h, w], `image_latents` [3N, 4, h, w], pose [1, N, 4].
    pub fn predict_v(&self, latents: &Tensor, image_latents: &Tensor, t: usize, context: &Tensor, pose: &Tensor) -> Result<Tensor> {
        let num_views = pose.dim(1)?;
        let x = Tensor::cat(&[latents, image_latents], 1)?;
        self.unet.forward(&x, t as f32, context, pose, num_views)
    }

    /// DDIM sampling from `init_noise` [3N, 4, h, w]. `step_noise(k)` supplies z for step k when
    /// η > 0; `observe` sees every step.
    // Mirrors the reference signature: the inputs of `IDArbDiffusionPipeline.__call__`'s denoising loop (image, pose, latents, eta, generator, callback) plus its scheduler.
    #[allow(clippy::too_many_arguments)]
    pub fn denoise(
        &self,
        image_latents: &Tensor,
        pose: &Tensor,
        init_noise: &Tensor,
        scheduler: &DdimScheduler,
        eta: f32,
        step_noise: &mut dyn FnMut(usize) -> Result<Tensor>,
        observe: &mut dyn FnMut(StepReport) -> Result<()>,
    ) -> Result<Tensor> {
        let num_views = pose.dim(1)?;
        let context = self.context(num_views)?;
        let mut latents = init_noise.clone();
        for (k, &t) in scheduler.timesteps.iter().enumerate() {
            let v = self.predict_v(&latents, image_latents, t, &context, pose)?;
            let noise = if eta > 0.0 { Some(step_noise(k)?) } else { None };
            latents = scheduler.step(k, &v, &latents, eta, noise.as_ref())?;
            observe(StepReport { step: k, timestep: t, v_pred: &v, latents: &latents })?;
        }
        Ok(latents)
    }

    /// Latents → images in [0, 1]: `(decode(z/s)/2 + 0.5).clamp(0, 1)`. [3N, 3, H, W].
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        // one image at a time bounds the decoder's memory at 512² (its activations are large)
        let parts = (0..latents.dim(0)?)
            .map(|i| self.vae.decode_scaled(&latents.narrow(0, i, 1)?)?.affine(0.5, 0.5)?.clamp(0f32, 1f32))
            .collect::<Result<Vec<_>>>()?;
        Tensor::cat(&parts, 0)
    }
}

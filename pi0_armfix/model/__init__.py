"""pi0 in Flax: a PaliGemma prefix and an action expert that share every attention layer.

Sizes live in `config.py` (presets `pi0`, `demo`, `tiny`); the functional API over a plain nested
dict of float32 parameters with openpi's names is in `flow_model.py`. This docstring is the spec the
PyTorch mirror (`pi0_armfix/torch_mirror/model.py`) matches. It follows openpi's pi0
(`src/openpi/models/{pi0,gemma,siglip}.py`); deviations are marked DEVIATION.

Notation: B batch, P prefix length, S suffix length = 1 + H, H action_horizon, A action_dim,
W = paligemma.width, E = action_expert.width, N heads, K kv heads, G = N / K, Dh head_dim.
`dtype` is the activation dtype (config.dtype); params are float32 and cast to `dtype` at each
matmul ("w.astype(x.dtype)"); attention logits and norm statistics are float32.

Observation -> model inputs (`inputs.py`)
  * image[key] uint8 [B, h, w, 3] -> float32 `x / 255 * 2 - 1` in [-1, 1] (float images are taken
    as already in [-1, 1]); if (h, w) != image_resolution: resize_with_pad = scale by
    1 / max(h / H_img, w / W_img) with `jax.image.resize(method="linear")` (antialiased when
    shrinking), to (int(h / ratio), int(w / ratio)), then pad symmetrically (extra row/column at the
    bottom/right) with -1.0. Train-time augmentation (train=True only) happens after that, in
    [0, 1] space (`x / 2 + 0.5`, back with `* 2 - 1`); it is not part of the mirror's contract.
  * cameras are used in `config.image_keys` order; image_mask[key] False masks all its tokens.

Prefix (bidirectional, ar_mask = 0 for every token)
  * SigLIP per camera (weights shared across cameras), all in `dtype` except the stem:
      patches = Conv(kernel=stride=patch, VALID)(image) in float32 -> [B, n, width] (row-major
      h x w patches) + pos_embedding[1, n, width] (float32); cast to dtype;
      depth x pre-LN block: x += MHA(LayerNorm_0(x)); x += MlpBlock_0(LayerNorm_1(x)) with
        LayerNorm eps 1e-6 (mean/var, scale and bias), MHA = query/key/value DenseGeneral with bias
        -> [.., heads, width/heads], q scaled by (width/heads)**-0.5, softmax, out DenseGeneral with
        bias; MlpBlock = Dense_0 -> gelu (tanh approximation) -> Dense_1;
      encoder_norm (LayerNorm); head = Dense(W) with bias. No pooling: n tokens per camera.
  * text: embedder.input_embedding[tokens] * sqrt(W) (scale applied in float32), cast to dtype.
  * prefix = concat(camera tokens..., text tokens) [B, P, W];
    prefix_mask = concat(repeat(image_mask[key], n)..., tokenized_prompt_mask) [B, P].

Suffix (action expert)
  * state token: state_proj(state) [B, 1, E] (Dense with bias, float32 inputs); ar_mask = 1.
  * time embedding: posemb_sincos(t, E, min_period=4e-3, max_period=4.0):
      fraction = linspace(0, 1, E / 2); period = min * (max / min) ** fraction;
      arg = t[:, None] * (2 pi / period)[None]; emb = concat(sin(arg), cos(arg)) -> [B, E].
  * action tokens: h = concat(action_in_proj(x_t) [B, H, E], repeat(emb, H)) [B, H, 2E];
      h = action_time_mlp_out(swish(action_time_mlp_in(h))) [B, H, E]; ar_mask = 1, 0, ..., 0.
  * suffix = concat(state token, action tokens) [B, S, E]; suffix mask all True.

Attention mask and positions (openpi's make_attn_mask)
  * c = cumsum(ar_mask over the whole sequence); token i may attend to token j iff
    c[j] <= c[i] and mask[i] and mask[j]. Result: the prefix is one bidirectional block that never
    sees the suffix; the state token sees the prefix and itself; action tokens see the prefix, the
    state and every action token; padded tokens are never attended to.
  * positions = cumsum(mask) - 1 over the concatenated sequence (padded tokens share a position
    with their predecessor; they are masked anyway).

Transformer (`gemma.py`, depth layers scanned, params stacked on a leading depth axis)
  Each expert e in (prefix, suffix) has its own weights (names of the action expert end in "_1"),
  one joint attention over the concatenated sequence:
    per layer:
      y_e = RMSNorm_e(x_e), RMSNorm(x) = x * rsqrt(mean(x**2 in float32) + 1e-6) * (1 + scale),
            scale initialised to 0, result cast back to dtype;
      q_e = einsum("BTD,NDH->BTNH", y_e, q_einsum_e); k_e, v_e = einsum("BSD,2KDH->2BSKH", y_e,
            kv_einsum_e); q, k, v = concatenation over experts along the sequence axis;
      RoPE (half-split, base 10_000) on q and k: freq_exponents = 2 * arange(Dh / 2) / Dh,
            timescale = 10_000 ** freq_exponents, rad = positions[..., None] / timescale,
            x1, x2 = split(x, 2, -1); rope(x) = concat(x1 cos - x2 sin, x2 cos + x1 sin)
            (computed in float32, cast back to dtype);
      q *= Dh ** -0.5 (after RoPE); no logit softcap;
      grouped-query attention: query head n uses kv head n // G;
            logits (float32) = q . k; masked entries set to -2.3819763e38; softmax in float32,
            probabilities cast to dtype; encoded = probs . v -> [B, T, N, Dh];
      o_e = einsum("BTNH,NHD->BTD", encoded[expert's rows], attn_vec_einsum_e); x_e += o_e;
      x_e += mlp_e(RMSNorm'_e(x_e)) with mlp(x) = (gelu_tanh(x @ gating_einsum[0]) *
            (x @ gating_einsum[1])) @ linear (gated GELU, tanh approximation).
    final_norm_e (RMSNorm) on each expert's output.
  The KV cache of a layer is its (k, v) after RoPE, [B, P, K, Dh] per layer (stacked over depth).

Outputs
  * v = action_out_proj(suffix_out[:, 1:]) [B, H, A] (the H action tokens), in float32.
  * Flow matching (docs/design.md §3): t ~ Beta(1.5, 1) * 0.999 + 0.001,
    x_t = t * noise + (1 - t) * a, u = noise - a, per-dim error e = (v - u)**2 [B, H, A], then `pi0_armfix.loss.training_loss`.
  * Sampling: prefix KV cache once, x <- x + dt * v(x, t), t <- t + dt, dt = -1 / num_steps,
    num_steps Euler steps from t = 1 (x = noise) to t = 0.

DEVIATION: the SigLIP head is initialised with lecun-normal (openpi zero-inits it, which is
irrelevant for pretrained weights but makes a from-scratch model blind at step 0). Initialisation
is not part of the mirror's contract; only the forward computation and the names are.
"""

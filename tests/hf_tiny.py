"""Tiny randomly initialised models of the real estimator architectures, saved as local snapshots.

As transformers' and diffusers' own test suites do (tests/models/depth_pro, tests/models/depth_anything,
tests/pipelines/marigold): the real model classes built from small configs, saved with ``save_pretrained`` and
loaded back through ``from_pretrained(folder)``, the path a user's ``--model-path`` takes. No network: the
CLIP tokenizer is built from a vocabulary written here. Each snapshot carries the files a hub snapshot has
(config, weights, ``preprocessor_config.json`` / ``model_index.json`` with the published checkpoints'
``target_properties``), only small.
"""
from __future__ import annotations

import json
from pathlib import Path

#: target_properties as the published Marigold v1-1 checkpoints declare them (see usdrelight.estimate.hf_decomposition)
LIGHTING_TARGETS = {"target_names": ["albedo", "shading", "residual"],
                    "albedo": {"prediction_space": "linear", "up_to_scale": False},
                    "shading": {"prediction_space": "linear", "up_to_scale": True},
                    "residual": {"prediction_space": "linear", "up_to_scale": True}}
APPEARANCE_TARGETS = {"target_names": ["albedo", "material"], "albedo": {"prediction_space": "srgb"},
                      "material": {"prediction_space": "stack", "sub_target_names": ["roughness", "metallicity", None]},
                      "roughness": {"prediction_space": "linear"}, "metallicity": {"prediction_space": "linear"}}


def depth_pro(folder: Path) -> Path:
    import torch
    from transformers import DepthProConfig, DepthProForDepthEstimation

    vit = {"model_type": "dinov2", "num_hidden_layers": 1, "hidden_size": 16, "num_attention_heads": 1,
           "patch_size": 4, "intermediate_size": 16}
    cfg = DepthProConfig(patch_size=16, fusion_hidden_size=16, intermediate_hook_ids=[0],
                         intermediate_feature_dims=[8], scaled_images_ratios=[0.5, 1.0],
                         scaled_images_overlap_ratios=[0.0, 0.25], scaled_images_feature_dims=[8, 8],
                         image_model_config=vit, patch_model_config=vit, fov_model_config=vit, use_fov_model=True)
    torch.manual_seed(0)
    DepthProForDepthEstimation(cfg, use_fov_model=True).save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps({
        "image_processor_type": "DepthProImageProcessor", "do_normalize": True, "do_rescale": True,
        "do_resize": True, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5], "resample": 2,
        "rescale_factor": 1 / 255, "size": {"height": 32, "width": 32}}))
    return folder


def depth_anything(folder: Path, metric: bool = False) -> Path:
    import torch
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    backbone = Dinov2Config(image_size=28, patch_size=14, hidden_size=8, num_hidden_layers=2, num_attention_heads=2,
                            intermediate_size=8, out_indices=[1, 2], reshape_hidden_states=False)
    cfg = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=8, patch_size=14,
                              neck_hidden_sizes=[4, 4], fusion_hidden_size=6, head_hidden_size=4,
                              reassemble_factors=[1, 1], depth_estimation_type="metric" if metric else "relative",
                              max_depth=20 if metric else 1)
    torch.manual_seed(0)
    model = DepthAnythingForDepthEstimation(cfg)
    with torch.no_grad():  # random weights give ~0 after the head's ReLU: lift the output as a trained one is
        model.head.conv3.bias.fill_(1.0)
        model.head.conv3.weight.mul_(100.0)
    model.save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps({
        "image_processor_type": "DPTImageProcessor", "do_normalize": True, "do_rescale": True, "do_resize": True,
        "do_pad": False, "ensure_multiple_of": 14, "keep_aspect_ratio": True, "image_mean": [0.485, 0.456, 0.406],
        "image_std": [0.229, 0.224, 0.225], "resample": 3, "size": {"height": 42, "width": 42}}))
    return folder


def clip_tokenizer(folder: Path):
    """A CLIP tokenizer over a 60-token vocabulary (BOS/EOS and letters), written to ``folder``."""
    from transformers import CLIPTokenizer

    folder.mkdir(parents=True, exist_ok=True)
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for i, c in enumerate("abcdefghijklmnopqrstuvwxyz"):
        vocab[c], vocab[c + "</w>"] = 2 + i, 30 + i
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    return CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), model_max_length=8), len(vocab)


def marigold(folder: Path, targets: dict) -> Path:
    """A MarigoldIntrinsicsPipeline (UNet, VAE, DDIM scheduler, CLIP text encoder and tokenizer) with
    ``targets`` (its target_properties), processing at 32 px in one denoising step."""
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, MarigoldIntrinsicsPipeline, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    n = len(targets["target_names"])
    tok, n_vocab = clip_tokenizer(folder.parent / (folder.name + "-vocab"))
    torch.manual_seed(0)
    unet = UNet2DConditionModel(block_out_channels=(8, 16), layers_per_block=1, sample_size=8,
                                in_channels=4 * (n + 1), out_channels=4 * n, attention_head_dim=2, norm_num_groups=4,
                                down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                                up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), cross_attention_dim=8)
    vae = AutoencoderKL(block_out_channels=[8, 16], in_channels=3, out_channels=3, latent_channels=4,
                        down_block_types=["DownEncoderBlock2D"] * 2, up_block_types=["UpDecoderBlock2D"] * 2,
                        norm_num_groups=4, layers_per_block=1)
    scheduler = DDIMScheduler(beta_start=0.00085, beta_end=0.012, prediction_type="v_prediction",
                              set_alpha_to_one=False, steps_offset=1, beta_schedule="scaled_linear",
                              clip_sample=False, thresholding=False, timestep_spacing="trailing")
    text = CLIPTextModel(CLIPTextConfig(bos_token_id=0, eos_token_id=1, pad_token_id=1, hidden_size=8,
                                        intermediate_size=16, num_attention_heads=2, num_hidden_layers=1,
                                        vocab_size=n_vocab, max_position_embeddings=8, projection_dim=8))
    pipe = MarigoldIntrinsicsPipeline(unet=unet, vae=vae, scheduler=scheduler, text_encoder=text, tokenizer=tok,
                                      prediction_type="intrinsics", target_properties=targets,
                                      default_denoising_steps=1, default_processing_resolution=32)
    pipe.save_pretrained(folder)
    return folder


def make_all(root: Path) -> dict:
    """Every tiny snapshot under ``root``: name -> folder."""
    root.mkdir(parents=True, exist_ok=True)
    return {"depth-pro": depth_pro(root / "depth-pro"),
            "depth-anything-v2": depth_anything(root / "depth-anything-v2"),
            "marigold-iid-lighting": marigold(root / "marigold-iid-lighting", LIGHTING_TARGETS),
            "marigold-iid-appearance": marigold(root / "marigold-iid-appearance", APPEARANCE_TARGETS)}

#!/usr/bin/env python3
"""openpi's PyTorch pi0 / pi0.5 as the same-run baseline of chunkrt's inference bench.

The bench (`cargo bench --bench inference -- --openpi DIR`) starts this worker once per bench
configuration and asks it for one `sample_actions` call per round, between its own calls, so a
slow period of the machine hits both programs alike. Protocol (one line each way, JSON out):

    worker -> {"ready": true, "torch": ..., "params": ..., "threads": ..., "cpu_capability": ...}
    bench  -> sample            worker -> {"wall_us": ..., "cpu_us": ...}
    bench  -> quit  (or EOF)

The model is openpi's own `PI0Pytorch` from the checkout given with --openpi (nothing of it is
copied here), built at the sizes of a chunkrt bench configuration (`benches/data/*_bench.json`)
with random weights, float32, eager, torch.no_grad, `float32_matmul_precision("highest")`, the
same camera count, prompt length and valid-token count as chunkrt's side, 10 denoising steps.
`scripts/openpi-env.sh` makes a Python with the versions openpi pins.

Run alone to check a setup: `python3 scripts/openpi_worker.py --openpi DIR --config
benches/data/pi0_bench.json --check`.
"""

import argparse
import json
import os
import sys
import time


def openpi_root(path):
    """The folder holding the `openpi` package: DIR itself or DIR/src (a git checkout)."""
    for cand in (path, os.path.join(path, "src")):
        if os.path.isfile(os.path.join(cand, "openpi", "models_pytorch", "pi0_pytorch.py")):
            return cand
    raise SystemExit(f"openpi_worker: no openpi/models_pytorch/pi0_pytorch.py under {path} or {path}/src")


def build(cfg, threads, seed):
    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    import openpi.models.gemma as gemma
    import openpi.models_pytorch.gemma_pytorch as gemma_pt
    import openpi.models_pytorch.pi0_pytorch as pi0_pt
    import openpi.models_pytorch.preprocessing_pytorch as prep
    from openpi.models.pi0_config import Pi0Config

    def expert(d):
        return gemma.Config(
            width=d["width"],
            depth=d["depth"],
            mlp_dim=d["mlp_dim"],
            num_heads=d["num_heads"],
            num_kv_heads=d["num_kv_heads"],
            head_dim=d["head_dim"],
        )

    # openpi names its sizes by variant; the bench sizes are added as two more variants.
    sizes = {"bench_vlm": expert(cfg["paligemma"]), "bench_expert": expert(cfg["action_expert"])}
    upstream_get_config = gemma.get_config
    gemma.get_config = lambda v: sizes[v] if v in sizes else upstream_get_config(v)

    # openpi sizes SigLIP for the full model; the bench's vision tower is smaller.
    vis = cfg["vision"]
    upstream_paligemma = gemma_pt.PaliGemmaForConditionalGeneration

    def sized_paligemma(config):
        v = config.vision_config
        v.hidden_size = vis["hidden_size"]
        v.num_hidden_layers = vis["num_hidden_layers"]
        v.num_attention_heads = vis["num_attention_heads"]
        v.intermediate_size = vis["intermediate_size"]
        v.patch_size = vis["patch_size"]
        v.image_size = vis["image_size"]
        v.layer_norm_eps = vis["layer_norm_eps"]
        v.projection_dim = cfg["paligemma"]["width"]
        return upstream_paligemma(config=config)

    gemma_pt.PaliGemmaForConditionalGeneration = sized_paligemma

    # the bench's cameras, not openpi's default three
    cameras = tuple(cfg["cameras"])
    upstream_prep = prep.preprocess_observation_pytorch
    prep.preprocess_observation_pytorch = lambda obs, **kw: upstream_prep(obs, image_keys=cameras, **kw)

    model_cfg = Pi0Config(
        dtype="float32",
        paligemma_variant="bench_vlm",
        action_expert_variant="bench_expert",
        action_dim=cfg["action_dim"],
        action_horizon=cfg["action_horizon"],
        max_token_len=cfg["max_token_len"],
        pi05=cfg["pi05"],
        pytorch_compile_mode=None,
    )
    model = pi0_pt.PI0Pytorch(model_cfg).eval()
    # openpi's constructor asks for "high" (TF32 on GPUs); the bench compares full f32
    torch.set_float32_matmul_precision("highest")

    s = cfg["image_size"]
    lt = cfg["max_token_len"]
    valid = cfg.get("valid_prompt_tokens", lt)

    class Obs:
        pass

    obs = Obs()
    obs.images = {k: torch.rand(1, 3, s, s) * 2 - 1 for k in cameras}
    obs.image_masks = {k: torch.ones(1, dtype=torch.bool) for k in cameras}
    obs.state = torch.randn(1, cfg["action_dim"])
    obs.tokenized_prompt = (torch.arange(lt) * 7919 % cfg["vocab_size"]).reshape(1, lt)
    obs.tokenized_prompt_mask = (torch.arange(lt) < valid).reshape(1, lt)
    obs.token_ar_mask = None
    obs.token_loss_mask = None
    noise = torch.randn(1, cfg["action_horizon"], cfg["action_dim"])
    steps = cfg.get("num_denoise_steps", 10)
    params = sum(p.numel() for n, p in model.named_parameters() if "embed_tokens" not in n and "lm_head" not in n)

    def sample():
        with torch.no_grad():
            return model.sample_actions("cpu", obs, noise=noise.clone(), num_steps=steps)

    return torch, sample, params


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--openpi", required=True, help="openpi checkout (or its src/ folder)")
    ap.add_argument("--config", required=True, help="bench configuration JSON (benches/data/*_bench.json)")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--check", action="store_true", help="build, run one warm-up and one timed sample, print, exit")
    args = ap.parse_args()
    os.environ.setdefault("USE_TF", "0")
    os.environ.setdefault("USE_FLAX", "0")
    sys.path.insert(0, openpi_root(args.openpi))
    with open(args.config) as f:
        cfg = json.load(f)
    torch, sample, params = build(cfg, args.threads, args.seed)
    actions = sample()  # warm-up (first-call allocations, oneDNN primitive creation)
    if not bool(torch.isfinite(actions).all()):
        raise SystemExit("openpi_worker: non-finite actions from the openpi model")
    hello = {
        "ready": True,
        "torch": torch.__version__,
        "params": params,
        "threads": torch.get_num_threads(),
        # ATen's vectorised kernels (ATEN_CPU_CAPABILITY caps them), e.g. "AVX2", "AVX512"
        "cpu_capability": getattr(torch.backends.cpu, "get_cpu_capability", lambda: "?")(),
        "actions_shape": list(actions.shape),
    }
    print(json.dumps(hello), flush=True)
    lines = iter(["sample", "quit"]) if args.check else sys.stdin
    for line in lines:
        cmd = line.strip()
        if cmd == "sample":
            c0, t0 = time.process_time(), time.perf_counter()
            sample()
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            print(json.dumps({"wall_us": round(wall * 1e6), "cpu_us": round(cpu * 1e6)}), flush=True)
        elif cmd in ("quit", ""):
            break
        else:
            print(json.dumps({"error": f"unknown command {cmd!r}"}), flush=True)


if __name__ == "__main__":
    main()

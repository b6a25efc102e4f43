"""Train a bundled tiny model on the reaching task: `python -m openpi_cam.demo.train --out DIR [--model pi05]`
(the Meta-World model trains on recorded demonstrations through `python -m openpi_cam.cli.train_demo --sim metaworld`).

One reproducible command (fixed seeds, CPU): norm stats from task data (upstream's quantile format) -> the tokenizers
-> the family's training format -> AdamW on the family's loss (`TrainArgs`) ->
`<out>/checkpoint/{params, assets/demo_reach/norm_stats.json}` -> closed-loop success rate in the simulator.
pi0-FAST: upstream's FAST format (prefix `Task: ..., State: ...;\\n`, postfix `Action: ` + FAST ids + `|` + EOS, loss on
the postfix), in two phases. pi0.5: the prompt with the discretised state, and the flow-matching loss at a fresh
noise and time (t ~ Beta(1.5, 1) * 0.999 + 0.001, as upstream) for every example of every step.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import optax
import tyro

from openpi_cam.checkpoints import model_spec
from openpi_cam.demo import bundled, make_tokenizers, metaworld_loop, metaworld_sim, sim, train_state
from openpi_cam.demo.data import Batches, write_norm_stats
from openpi_cam.demo.metaworld_data import Demonstrations
from openpi_cam.demo.quality import binding_probe
from openpi_cam.model import pi0
from openpi_cam.model.checkpoint import load_params, save_params
from openpi_cam.model.config import Pi0Config, Pi0FASTConfig
from openpi_cam.model.pi0_fast import compute_loss, init_params
from openpi_cam.policies import demo_reach
from openpi_cam.policies.config import PolicyConfig


@dataclasses.dataclass(frozen=True)
class TrainArgs:
    """Defaults: 5,000 steps at upstream's training positions, then 400 at the positions upstream's decoder serves
    (about 22 minutes on 2 CPU cores). The shipped model is the longer recipe `--steps 10000 --finetune-steps 0`,
    then `--steps 0 --init-from <params> --finetune-steps 800` (README, "The bundled demo")."""

    model: Literal["pi0_fast", "pi05"] = "pi0_fast"  # the family: pi0-FAST (action tokens) or pi0.5 (flow matching)
    out: Path | None = None  # None: the bundled assets of `model`
    steps: int = 5000  # optimizer steps of the first phase (0: none, e.g. to fine-tune from --init-from alone)
    batch_size: int = 32  # examples per step
    lr: float = 2e-3  # the first phase's peak learning rate (AdamW; warmup, then cosine decay to 5% of it)
    warmup: int = 50  # steps of linear warmup to --lr
    seed: int = 0  # the initialisation, the text tokenizer and the batches
    width: int = 128  # the language model's width (pi0.5's action expert keeps its own, 64)
    depth: int = 2  # the language model's layers
    vit_width: int = 64  # the vision encoder's width
    patch_size: int = bundled.PATCH_SIZE  # the vision encoder's patch side, in pixels
    # Batches of (same scene, two prompts) pairs (`task.contrast_pair`): without them the model settles on "head for
    # a block" and never binds the colour the prompt names (training curves: docs/DEMO_NOTES.md).
    contrast_pairs: bool = True
    # RoPE offset of the action tokens in the first phase: 0 is where upstream's training puts them.
    decode_offset: int = 0
    # Second phase: a fresh optimizer trains the action tokens one position on, where upstream's decoder serves them
    # (quirk 1): trained at upstream's training positions only, the model binds the colour yet, served, decodes
    # toward the named block much less often than with the decoder's offset removed (docs/DEMO_NOTES.md). 0: no phase.
    # (pi0-FAST only; the phase is skipped for pi0.5.)
    finetune_steps: int = 400
    finetune_lr: float = 1e-3  # the second phase's peak learning rate (a fresh AdamW, same schedule)
    finetune_warmup: int = 20  # the second phase's warmup steps
    init_from: Path | None = None  # a params directory to start from instead of a fresh initialisation
    eval_episodes: int = 30  # closed-loop episodes run after training, their success logged (0: none)
    log_every: int = 250  # log the training loss every this many steps
    probe_every: int = 500  # log the binding probe (`quality.binding_probe`) every this many steps; 0: never
    # Write the run's state (`demo.train_state`) every this many steps, for --resume to continue from (0: only when
    # a SIGTERM or SIGINT stops the run).
    save_every: int = 0
    resume: bool = False  # continue the stopped run whose state is in --out (same flags and data)

    def unused(self) -> str | None:
        """The fields set (other than their defaults) that the others leave without effect, or None: what the
        training commands refuse rather than ignore."""
        finetune = [f"--{n.replace('_', '-')}" for n in ("finetune_lr", "finetune_warmup") if self._changed(n)]
        if finetune and (self.finetune_steps == 0 or self.model == "pi05"):
            return f"{', '.join(finetune)}: no finetune phase runs (--finetune-steps 0, or pi0.5, which has none)"
        if self.model == "pi05" and self._changed("decode_offset"):
            return "--decode-offset: pi0.5 has no action tokens to place"
        return None

    def _changed(self, name: str) -> bool:
        return getattr(self, name) != getattr(TrainArgs, name)


@dataclasses.dataclass(frozen=True)
class Phase:
    name: str
    steps: int
    lr: float
    warmup: int
    decode_offset: int


def run_episode(policy, seed: int, *, max_calls: int = 8, execute: int = 5) -> tuple[bool, int]:
    """Closed loop: infer a chunk, execute its first `execute` actions, repeat until success or `max_calls`."""
    episode = sim.new_episode(seed)
    for call in range(max_calls):
        obs = bundled.policy_input(bundled.client_observation(episode.observe()))
        if episode.execute(policy.infer(obs)["actions"], execute):
            return True, call + 1
    return False, max_calls


def evaluate(
    out: Path, episodes: int, model: str, seed: int = 10_000, tasks: tuple[str, ...] = (), image_size: int | None = None
) -> float:
    """Closed-loop success rate of the model trained into `out` over fresh episodes of its task (Meta-World: episode
    e of task e modulo the `tasks`, cameras at `image_size` px)."""
    policy = model_spec.create_demo_policy(model=model, assets=out)
    if tasks:
        infer = lambda obs: policy.infer(bundled.policy_input(obs))  # noqa: E731
        outcomes = []
        for e in range(episodes):
            task_name = tasks[e % len(tasks)]
            outcomes.append(
                metaworld_loop.run_episode(infer, seed + e, task=task_name, image_size=image_size)["success"]
            )
            print(f"evaluation episode {e + 1}/{episodes} ({task_name}): {sum(outcomes)} successes", flush=True)
        return float(np.mean(outcomes))
    return float(np.mean([run_episode(policy, seed + e)[0] for e in range(episodes)]))


def phases(args: TrainArgs) -> list[Phase]:
    main = Phase("main", args.steps, args.lr, args.warmup, args.decode_offset)
    finetune = Phase("finetune", args.finetune_steps, args.finetune_lr, args.finetune_warmup, 1)
    return [p for p in (main, finetune) if p.steps > 0 and (p is main or args.model == "pi0_fast")]


ModelConfig = Pi0FASTConfig | Pi0Config


def model_config(args: TrainArgs, robot: PolicyConfig | None = None, image_size: int | None = None) -> ModelConfig:
    """The architecture `args` describe for the demo robot `robot` (None: the reaching demo's) at `image_size` px (None:
    the reaching task's)."""
    sizes = {"width": args.width, "depth": args.depth, "vit_width": args.vit_width, "patch_size": args.patch_size}
    if image_size is not None:
        sizes["image_size"] = image_size
    if robot is not None:
        sizes["robot"] = robot
    if args.model == "pi05":
        return bundled.pi05_model_config(make_tokenizers.VOCAB_SIZE, **sizes)
    return bundled.model_config(make_tokenizers.VOCAB_SIZE, **sizes)


def example_losses(cfg: ModelConfig, decode_offset: int) -> Callable:
    """`losses(params, batch, key) -> [B]`: the family's per-example training loss (pi0.5: at the noise and time
    `key` draws; the same key gives the same draws, which makes two batches' losses comparable)."""
    if isinstance(cfg, Pi0FASTConfig):
        return lambda params, batch, key: compute_loss(params, batch.obs, cfg, decode_offset=decode_offset)

    def flow_losses(params, batch, key):
        noise_key, time_key = jax.random.split(key)
        noise = jax.random.normal(noise_key, batch.actions.shape)
        t = jax.random.beta(time_key, 1.5, 1.0, batch.actions.shape[:1]) * 0.999 + 0.001
        return jnp.mean(pi0.compute_loss(params, batch.obs, batch.actions, noise, t, cfg=cfg), axis=-1)

    return flow_losses


def train(
    args: TrainArgs,
    demonstrations: Demonstrations | None = None,
    config: PolicyConfig | None = None,
    *,
    vocabulary: tuple[str, ...] = (),
    eval_tasks: tuple[str, ...] = (),
) -> dict:
    """Trains on the reaching task, or on recorded `demonstrations` for the bundled robot `config` names (its assets
    are the default `--out`; the binding probe is the reaching task's and is skipped). The text tokenizer learns the
    demonstrations' prompts and the `vocabulary` prompts (instructions the model may be sent but was not trained on);
    the evaluation drives the Meta-World `eval_tasks` in turn."""
    bundled_name = args.model if config is None else model_spec.BUNDLED_MODELS[config.name]
    out = output_dir(args, config)
    out.mkdir(parents=True, exist_ok=True)
    # The data digest (a pass over every frame) is taken only when a state is read or written.
    run = functools.cache(lambda: run_identity(args, demonstrations))
    saved = train_state.read(out, run(), run_identity(TrainArgs(), None)) if args.resume else None
    image_size = None
    if demonstrations is None:
        normalize = write_norm_stats(out)
        make_tokenizers.train_sentencepiece(out, seed=args.seed)
    else:
        asset_id = config.asset_id if config is not None else demo_reach.ASSET_ID
        normalize = write_norm_stats(out, demonstrations=demonstrations, asset_id=asset_id)
        prompts = tuple(sorted(set(demonstrations.prompt.tolist()) | set(vocabulary)))
        make_tokenizers.train_sentencepiece(out, seed=args.seed, prompts=prompts, state_dim=metaworld_sim.STATE_DIM)
        args = dataclasses.replace(args, probe_every=0)
        image_size = int(demonstrations.base_image.shape[1])
    if args.model == "pi0_fast":
        chunks = None if demonstrations is None else demonstrations.all_chunks(config.action_horizon)
        fast = make_tokenizers.fit_fast(out, lambda c: normalize({"actions": c})["actions"], chunks=chunks)
        print(f"FAST: {fast.bpe_vocab_size} ids", flush=True)
    cfg = model_config(args, config, image_size)
    init = init_params if args.model == "pi0_fast" else pi0.init_params
    params = init(cfg, jax.random.key(args.seed)) if args.init_from is None else load_params(args.init_from)
    batches = Batches(
        out,
        normalize,
        args.batch_size,
        args.seed + 1,
        contrast_pairs=args.contrast_pairs,
        family=args.model,
        demonstrations=demonstrations,
        config=config,
    )
    names = [p.name for p in phases(args)]
    t0, summary = time.time(), {}
    for phase in phases(args):
        if saved is not None and names.index(phase.name) < names.index(saved.phase):
            continue  # done before the stop
        resumed = saved if saved is not None and saved.phase == phase.name else None
        params, summary[f"{phase.name}_loss"] = train_phase(
            params, cfg, batches, phase, args, save=lambda state: train_state.save(out, run(), state), resumed=resumed
        )
    params_dir = out / demo_reach.CHECKPOINT.name / "params"
    shutil.rmtree(params_dir, ignore_errors=True)
    save_params(params_dir, params)
    train_state.remove(out)
    summary["train_seconds"] = round(time.time() - t0)
    if args.eval_episodes:
        summary["success_rate"] = evaluate(
            out, args.eval_episodes, bundled_name, tasks=eval_tasks, image_size=image_size
        )
    print(json.dumps(summary), flush=True)
    return summary


def adamw(lr: float | optax.Schedule) -> optax.GradientTransformation:
    """The demo's optimizer: global-norm clipping, then AdamW."""
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(lr, weight_decay=1e-4))


def training_step(losses: Callable, optimizer: optax.GradientTransformation) -> Callable:
    """`step(params, opt_state, batch, key) -> (params, opt_state, loss)`, jitted; params and optimizer state are
    donated. `losses` is `example_losses(...)`."""

    @functools.partial(jax.jit, donate_argnums=(0, 1))
    def step(params, opt_state, batch, key):
        mean_loss = lambda p: jnp.mean(losses(p, batch, key))  # noqa: E731
        loss, grads = jax.value_and_grad(mean_loss)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def output_dir(args: TrainArgs, config: PolicyConfig | None = None) -> Path:
    """Where the run writes: --out, or the bundled assets of the model it trains."""
    bundled_name = args.model if config is None else model_spec.BUNDLED_MODELS[config.name]
    return model_spec.BUNDLED_ASSETS[bundled_name] if args.out is None else args.out


def resume_refused(args: TrainArgs, config: PolicyConfig | None = None) -> str | None:
    """Why --resume cannot continue (no state where the run writes), said before any data is read; or None."""
    absent = train_state.missing(output_dir(args, config)) if args.resume else None
    return None if absent is None else f"--resume: {absent}"


def run_identity(args: TrainArgs, demonstrations: Demonstrations | None) -> dict:
    """What a saved state must match to be resumed: every flag that decides a step, and the training frames."""
    flags = {f.name: getattr(args, f.name) for f in dataclasses.fields(args) if f.name not in train_state.FREE_FLAGS}
    run = {name: str(v) if isinstance(v, Path) else v for name, v in flags.items()}
    return run | {"data": None if demonstrations is None else demonstrations.digest}


def train_phase(
    params: dict,
    cfg: ModelConfig,
    batches: Batches,
    phase: Phase,
    args: TrainArgs,
    *,
    save: Callable[[train_state.Saved], Path],
    resumed: train_state.Saved | None = None,
) -> tuple[dict, float]:
    """AdamW (fresh state, or the `resumed` one's) on a warmup-cosine schedule; returns the params and the mean loss of
    the last log window. Hands the state to `save` every `--save-every` steps, and before stopping on a signal."""
    schedule = optax.warmup_cosine_decay_schedule(
        0.0, phase.lr, min(phase.warmup, phase.steps // 2), phase.steps, 0.05 * phase.lr
    )
    optimizer = adamw(schedule)
    opt_state = optimizer.init(params)
    start, losses = 0, []
    if resumed is not None:
        params, opt_state = resumed.restore(params, opt_state)
        batches.rng.bit_generator.state = resumed.rng
        start, losses = resumed.step, list(resumed.losses)
        print(f"{phase.name}: resumed after step {start}/{phase.steps}", flush=True)
    losses_fn = example_losses(cfg, phase.decode_offset)
    step = training_step(losses_fn, optimizer)
    probe_losses = jax.jit(losses_fn)
    probe_key = jax.random.key(args.seed + 2)
    keys = jax.random.split(jax.random.key(args.seed + 3), max(phase.steps, 1))
    t0 = time.time()
    with train_state.stop_request() as stop:
        for i in range(start, phase.steps):
            params, opt_state, loss = step(params, opt_state, batches(), keys[i])
            # Wait for the previous step only, so that Python builds the next batch while XLA runs this one.
            losses[-1:] = [float(x) for x in losses[-1:]]
            losses.append(loss)
            where = f"{phase.name} step {i + 1}/{phase.steps}"
            if (i + 1) % args.log_every == 0:
                print(f"{where} loss {np.mean(losses[-args.log_every :]):.4f} {time.time() - t0:.0f}s", flush=True)
            if args.probe_every and (i + 1) % args.probe_every == 0:
                probe = binding_probe(
                    lambda samples, p=params: np.asarray(probe_losses(p, batches.batch(samples), probe_key))
                )
                print(f"{where} binding probe {probe:.2f} (chance 0.5)", flush=True)
            if stop.signum is not None or (args.save_every and (i + 1) % args.save_every == 0):
                state = train_state.Saved.capture(phase.name, i + 1, batches.rng, losses, params, opt_state)
                print(f"{where}: state saved to {save(state)}", flush=True)
            if stop.signum is not None:
                name = signal.Signals(stop.signum).name
                raise train_state.Stopped(f"stopped by {name} after {where}: the same command with --resume continues")
    losses[-1:] = [float(x) for x in losses[-1:]]
    return params, float(np.mean(losses[-args.log_every :]))


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m openpi_cam.demo.train [FLAGS]`: the flags are `TrainArgs`; ones the others leave without effect are
    refused in one line."""
    args = tyro.cli(TrainArgs, args=argv)
    if refused := args.unused() or resume_refused(args):
        print(f"openpi_cam.demo.train: {refused}", file=sys.stderr)
        return 2
    try:
        train(args)
    except train_state.StateError as e:
        print(f"openpi_cam.demo.train: --resume: {e}", file=sys.stderr)
        return 2
    except train_state.Stopped as e:
        print(f"openpi_cam.demo.train: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

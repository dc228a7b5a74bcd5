"""What every family's training shares. A family object (one per family, in
``training/families/<family>.py``) is registered under the ``apcg.model_families`` entry points
(pyproject.toml) and found through :func:`apcg_core.families.get_family`. Everything that differs
between families lives in its module; nothing else asks which family it holds.

A family object provides:

* ``name``; ``load(directory, runtime)`` -> a model whose ``generate(conditions, count, seed)``
  makes clouds;
* ``train_options()`` -> the family-specific sizes it takes (name -> default);
* ``net_config(train_cfg, dataset)`` -> its network configuration (``to_dict()`` is saved with
  every checkpoint), ``networks(net_config)`` -> (generator or denoiser, critic or None);
* ``prepare(dataset)`` (once, off the training clock); ``batch(trainer, idx)`` -> the real
  batch of samples ``idx``; ``batches_per_step(cfg)``; ``train_step(trainer)`` -> one step's
  log row;
* ``export(state, header, out_dir, meta, data_dir, sampling_steps)`` -> the model directory
  (``export_reads(state)``: the directories it reads besides the run, never its output);
* ``untrained(model, out_dir, seed)`` -> the same network freshly initialised, loaded.
"""

from __future__ import annotations

from apcg_core.condition import NOISE_DIM
from apcg_core.errors import InputError

# torch (and the trainer and networks, which import it) is imported where it is used: opening a
# model through the registry runs on onnxruntime and must not wait for torch.


class Family:
    """What every family shares: sizes, refusing a sampling-step count, writing its model."""

    name: str
    sizes: tuple[str, ...] = ()  # the family-specific TrainConfig sizes it takes
    # the ablation's switches (TrainConfig names) its training reads; any other is refused
    switches: tuple[str, ...] = ()

    def train_options(self) -> dict:
        from ..trainer import size_defaults
        defaults = size_defaults()
        return {k: defaults[k] for k in self.sizes}

    def prepare(self, dataset) -> None:
        """Work on the training data done once, before the training clock starts."""

    def export_reads(self, state: dict) -> list[str]:
        """Directories the export reads besides the run (never written into by it)."""
        return []

    def check_sampling_steps(self, sampling_steps, state: dict) -> None:
        """Refuses a sampling-step count unless the family samples on a schedule."""
        if sampling_steps is not None:
            raise InputError(f"sampling_steps: the {self.name} family does not sample on a "
                             "schedule, so it takes no sampling-step count")

    def __repr__(self) -> str:
        return f"<model family {self.name}>"


class GANFamily(Family):
    """A generator against a critic, WGAN-GP (or BCE, the ablation's loss), ``n_critic``
    critic batches per generator step; every random draw from the step's own generator."""

    switches = ("loss", "n_critic")

    def batches_per_step(self, cfg) -> int:
        return cfg.n_critic

    def train_step(self, tr) -> dict:
        import torch
        import torch.nn.functional as F

        from ..trainer import gradient_penalty, step_generator
        cfg = tr.cfg
        wgan = cfg.loss == "wgan-gp"
        b = cfg.batch_size
        tr.G.train()
        tr.D.train()
        for j in range(cfg.n_critic):
            real, nu = tr.next_batch()
            gen = step_generator(cfg.seed, tr.step, j, tr.rank)
            z = torch.randn(b, NOISE_DIM, generator=gen)
            with tr.autocast():
                with torch.no_grad():
                    fake = tr.G(z, nu)
                d_real = tr.D(real, nu).float()
                d_fake = tr.D(fake, nu).float()
            if wgan:
                eps = torch.rand(b, generator=gen)
                gp = gradient_penalty(tr.D, real, fake.float(), nu, eps)
                loss_d = d_fake.mean() - d_real.mean() + cfg.gp_lambda * gp
            else:
                gp = torch.zeros(())
                loss_d = (F.binary_cross_entropy_with_logits(d_real, torch.ones_like(d_real))
                          + F.binary_cross_entropy_with_logits(d_fake, torch.zeros_like(d_fake)))
            tr.opt_d.zero_grad(set_to_none=True)
            loss_d.backward()
            tr.allreduce_grads(tr.D)
            tr.opt_d.step()
        gen = step_generator(cfg.seed, tr.step, cfg.n_critic, tr.rank)
        z = torch.randn(b, NOISE_DIM, generator=gen)
        with tr.autocast():
            score = tr.D(tr.G(z, nu), nu).float()
        loss_g = (-score.mean() if wgan else
                  F.binary_cross_entropy_with_logits(score, torch.ones_like(score)))
        tr.opt_g.zero_grad(set_to_none=True)
        loss_g.backward()
        tr.allreduce_grads(tr.G)
        tr.opt_g.step()
        tr.sync_buffers(tr.G)
        return tr.finish_step(loss_d, loss_g, gp, d_real.mean() - d_fake.mean())


__all__ = ["Family", "GANFamily"]

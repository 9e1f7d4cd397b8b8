"""The one place that knows how D4PG's pieces fit, from one ``ExperimentConfig``.

In the spirit of Acme's D4PG ``builder.py``: the replay table with its rate limiter, the n-step
writer, the learner's state, the behaviour policy, the environments and the evaluation protocol
are all made here. The serial trainer and every service (replay, learner, actor, scheduler) call
these methods and nothing else, so the two training modes cannot drift apart again (they once
trained at different batch sizes, warm-ups and exploration scales).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from curlnav.config import ExperimentConfig
from curlnav.layout import ObservationLayout
from curlnav.learner.networks import BehaviourPolicy
from curlnav.replay import NStepWriter, ReplayTable, SampleToInsertRatio

if TYPE_CHECKING:
    from curlnav.actor.service import ActorCore, ActorService, ActorServiceConfig
    from curlnav.learner.service import LearnerService, LearnerServiceConfig
    from curlnav.replay.service import ReplayService, ReplayServiceConfig
    from curlnav.sim import NamoEnv


class D4PGBuilder:
    """Makes every component of one experiment. ``config`` is never changed."""

    def __init__(self, config: ExperimentConfig) -> None:
        self.config = config
        self.layout = ObservationLayout.of(config.env, config.memory)

    # -- replay --------------------------------------------------------------------------------
    def make_rate_limiter(self) -> SampleToInsertRatio:
        """Reverb's SampleToInsertRatio with the replay section's ratio, warm-up and slack."""
        replay, batch = self.config.replay, self.config.d4pg.batch_size
        if replay.samples_per_insert == 0:  # no rate limit (benchmarks): sample once min_size is in
            return SampleToInsertRatio.unlimited(replay.min_size)
        limiter = SampleToInsertRatio(replay.samples_per_insert, replay.min_size, replay.error_buffer(batch))
        limiter.check_batch(batch, insert=replay.insert_batch)
        return limiter

    def batches_per_request(self, wanted: int) -> int:
        """The most batches (at most ``wanted``) one sample request may ask for: the rate limiter
        must be able to admit a request of that many transitions beside inserts of
        ``replay.insert_batch`` (``check_batch``), else inserts and samples could both wait for
        ever; and a request holds at most ``SampledBatch.MAX_BATCH`` transitions."""
        from curlnav.proto.messages import SampledBatch

        limiter, batch = self.make_rate_limiter(), self.config.d4pg.batch_size
        for k in range(min(max(1, wanted), max(1, SampledBatch.MAX_BATCH // batch)), 1, -1):
            try:
                limiter.check_batch(k * batch, insert=self.config.replay.insert_batch)
                return k
            except ValueError:
                continue
        return 1

    def make_replay_table(self) -> ReplayTable:
        replay = self.config.replay
        return ReplayTable(self.layout, replay.capacity, self.make_rate_limiter(),
                           "prioritized" if replay.prioritized else "uniform",
                           priority_exponent=replay.priority_exponent, seed=self.config.seed,
                           insert_batch=replay.insert_batch)

    def restore_replay_table(self, path) -> ReplayTable:
        """A saved table under this config's rate limiter (its own capacity and contents)."""
        return ReplayTable.restore(path, self.make_rate_limiter())

    def importance_weights(self, probabilities: np.ndarray, table_size: int) -> np.ndarray | None:
        """Importance-sampling weights ``(N P(i)) ** -beta``, max-normalised, for a prioritized
        sample; None for uniform sampling (every weight 1)."""
        if not self.config.replay.prioritized:
            return None
        weights = (1.0 / (max(table_size, 1) * np.maximum(probabilities, 1e-12))) ** self.config.replay.importance_exponent
        return (weights / weights.max()).astype(np.float32)

    # -- acting --------------------------------------------------------------------------------
    def make_nstep_writer(self) -> NStepWriter:
        return NStepWriter(self.layout, self.config.d4pg.n_step, self.config.d4pg.discount)

    def make_actor_loop(self, actor_index: int, policy: BehaviourPolicy, envs: int = 1):
        """Actor ``actor_index``'s loop of ``envs`` training environments: one batched call of
        ``policy`` per step of all of them, one n-step writer stream each (``VectorEpisodeLoop``)."""
        from curlnav.actor.vector import VectorEpisodeLoop, VectorNStepWriter

        if envs < 1:
            raise ValueError(f"an actor steps at least one environment, got {envs}")
        writer = VectorNStepWriter(self.layout, envs, self.config.d4pg.n_step, self.config.d4pg.discount)
        return VectorEpisodeLoop([self.make_env() for _ in range(envs)], self.make_acting_agent(policy).batch, writer,
                                 self.make_world_draws(actor_index), scenes=self.config.actor.scenes_per_process,
                                 helpers=self.make_training_helpers(actor_index, envs),
                                 memory=self.make_memories(envs))

    def make_memory(self):
        """One environment's network memory (``curlnav.memory.MemoryObserver``), or None when the
        network has none (``memory.beams`` 0)."""
        if not self.layout.memory_beams:
            return None
        from curlnav.memory import MemoryObserver

        return MemoryObserver(self.layout, self.config.env.lidar_fov)

    def make_memories(self, envs: int):
        """``envs`` memories (``make_memory``), or None without memory."""
        return None if not self.layout.memory_beams else [self.make_memory() for _ in range(envs)]

    def make_training_helpers(self, actor_index: int = 0, envs: int = 1, stream: int = 0):
        """The stack actor ``actor_index``'s network trains inside, one per environment
        (``helpers``; ``curlnav.nav.training.TrainingHelpers``), or None for the network alone.
        ``ValueError`` in one line where ``helpers.stack`` names nothing that trains in the loop."""
        stack = self.training_stack()
        if stack is None:
            return None
        from curlnav.nav.training import TrainingHelpers

        return TrainingHelpers(stack, self.config.env, envs, self.config.helpers, seed=(self.config.seed, actor_index),
                               stream=stream)

    def training_stack(self):
        """The ``NavStack`` of ``helpers.stack`` (``curlnav.nav.training.training_stack``), None for
        the network alone; ``ValueError`` in one line for one that cannot train in the loop."""
        spec = self.config.helpers.stack
        if not spec:
            return None
        from curlnav.config import INHERITED_HELPERS
        from curlnav.nav.training import training_stack

        shipped, source = None, self.config.init_from
        if spec == INHERITED_HELPERS:
            from curlnav.learner.init_from import inherited_stack

            shipped = inherited_stack(self.config.init_from)
        elif not spec.startswith("+"):
            shipped, source = self._stack_at(spec), spec
        return training_stack(spec, shipped, source)

    @staticmethod
    def _stack_at(path: str) -> dict | None:
        """The stack a ``helpers.stack`` path holds: a stack file's, or the one a policy artefact
        (or run, or checkpoint) ships; ``ValueError`` in one line beginning ``helpers.stack:``."""
        from pathlib import Path

        from curlnav.nav.stack import load_stack

        try:
            if Path(path).is_file() and Path(path).suffix in (".yaml", ".yml"):
                return load_stack(path).to_dict()
            if not Path(path).exists():
                raise ValueError(f"{path}: no such stack file or policy folder; helpers are suffixes (+rescue+shield), "
                                 f"inherit, a stack file (curlnav stack show AGENT --out FILE.yaml) or a policy folder")
            from curlnav.learner.init_from import inherited_stack

            return inherited_stack(path)
        except ValueError as exc:
            text = str(exc)
            raise ValueError(text if text.startswith("helpers.stack:") else f"helpers.stack: {text}") from None

    def make_acting_agent(self, policy: BehaviourPolicy) -> BehaviourPolicy:
        """What an actor's behaviour policy proposes with: ``curlnav.nav.build_stack`` of the network
        alone round it (one batched call steps an actor's K environments at once). The helpers it
        trains inside (``make_training_helpers``) act on each environment's proposal after it."""
        from curlnav.nav import NavStack, build_stack
        from curlnav.nav.stack import choose

        stack = NavStack(controller=choose("controller", "policy", path="behaviour policy"), label="behaviour policy")
        return build_stack(stack, self.config.env, controller=policy)[1]

    def make_behaviour_policy(self, actor_index: int = 0, actor_count: int = 1, stream: int = 0) -> BehaviourPolicy:
        """The policy actor ``actor_index`` of ``actor_count`` runs: random actions for its share
        of the warm-up (none when the networks start from a trained policy, ``init_from``), then
        the latest network with its rung of the sigma ladder. ``stream`` picks another noise
        sequence (a resumed run passes its step count)."""
        exploration = self.config.exploration
        warmup = 0 if self.config.init_from else exploration.warmup_share(actor_count)
        return BehaviourPolicy(self.layout, self.config.d4pg, sigma=exploration.sigma(actor_index),
                               warmup_steps=warmup,
                               rng=np.random.default_rng([self.config.seed, actor_index, stream]),
                               inference=self.config.actor.inference)

    def make_world_draws(self, actor_index: int = 0, stream: int = 0):
        """Actor ``actor_index``'s draws of worlds from distributions (``stream``: another
        sequence, as for the behaviour policy)."""
        from curlnav.worlds.distribution import WorldDraws

        return WorldDraws(seed=[self.config.seed, actor_index, stream, 28])

    def make_env(self, world=None, excluded_pairs: set | None = None) -> NamoEnv:
        """The training environment (episodes end at a base collision). On the experiment's own
        world, the evaluation protocol's held-out pairs are never drawn for training
        (``excluded_pairs``: those keys when the caller already has them, else drawn here)."""
        from curlnav.worlds.core.heldout import check_training_world

        check_training_world(world if world is not None else self.config.curriculum.world)  # never a held-out seed
        from curlnav.sim import NamoEnv  # here: the learner and the replay need no simulator

        env = NamoEnv(world if world is not None else self.config.curriculum.world, self.config.env)
        if world is None or world == self.config.curriculum.world:
            if excluded_pairs is None:
                from curlnav.evaluation.protocol import excluded_keys, held_out_pairs

                excluded_pairs = excluded_keys(held_out_pairs(self.config.curriculum.world,
                                                              self.config.evaluation.episodes))
            env.excluded_pairs = set(excluded_pairs)
        return env

    def make_eval_env(self, world=None) -> NamoEnv:
        """The evaluation environment (collisions counted, the trial goes on)."""
        from curlnav.sim import NamoEnv

        return NamoEnv(world if world is not None else self.config.curriculum.world, self.config.eval_env)

    # -- learning ------------------------------------------------------------------------------
    def make_learner_state(self, device=None, say=print):
        """The learner's ``D4PGState`` (networks, targets, optimisers): fresh, or from ``init_from``
        (``curlnav.learner.init_from``: checked against this experiment, ``ValueError`` in one line;
        ``say`` is told where the networks came from). Imported here so that actors, which use the
        rest of the builder, never load the learner's internals."""
        from curlnav.learner.d4pg import init_state

        if not self.config.init_from:
            return init_state(self.config.d4pg, self.layout, device)
        from curlnav.learner.init_from import check_starting_point, find_starting_point, starting_state

        point = find_starting_point(self.config.init_from)
        check_starting_point(point, self.config)
        return starting_state(point, self.config, self.layout, device, say)

    # -- services ------------------------------------------------------------------------------
    # The service shells take the parts made above and never import the builder; their modules are
    # imported here, inside the methods, so the serial trainer never loads Zenoh.
    def make_replay_service(self, cfg: ReplayServiceConfig) -> ReplayService:
        """The replay service of ``cfg`` around this experiment's table."""
        from curlnav.replay.service import ReplayService

        return ReplayService(cfg, self.config, self.make_replay_table())

    def make_actor_core(self, cfg: ActorServiceConfig) -> ActorCore:
        """The episode loop of actor ``cfg``, with its behaviour policy."""
        from curlnav.actor.service import ActorCore

        policy = self.make_behaviour_policy(cfg.actor_index, cfg.actor_count)
        return ActorCore(cfg, self.config, policy, self.make_actor_loop(cfg.actor_index, policy, cfg.envs))

    def make_actor_service(self, cfg: ActorServiceConfig) -> ActorService:
        """The actor service of ``cfg`` around ``make_actor_core``."""
        from curlnav.actor.service import ActorService

        return ActorService(cfg, self.config, self.make_actor_core(cfg))

    def make_learner_service(self, cfg: LearnerServiceConfig) -> LearnerService:
        """The learner service of ``cfg``: this builder is its ``LearnerParts``."""
        from curlnav.learner.service import LearnerService

        return LearnerService(cfg, self.config, self)

"""How a run acts on its Q network, as one composed part: greedily on Q, or through SG-D3QN's online
planner (``planning.enabled``).

A part wraps the Q network into the actor (:meth:`GreedyActing.actor`), carries the models the
actor reads (the planner's crowd predictor), brings their learners (:meth:`GreedyActing.learners`,
trained beside the Q network on the sampled batches) and names the replay-buffer keys those read
(:meth:`GreedyActing.stored_keys`). The trainer and the evaluation build their actor through it, so
neither branches on planning.

>>> from crowdrl.training import validate
>>> from crowdrl.training.facts import RunFacts
>>> run = validate({"preset": "smoke", "env": {"num_humans": 4}})
>>> acting = make_acting(run.planning, RunFacts.of(run), train=run.train, encoder=run.encoder.name, learn=True)
>>> type(acting).__name__, [type(x).__name__ for x in acting.learners()], acting.stored_keys()
('PlannedActing', ['PredictorLearner'], ['robot', 'humans', ('next', 'humans')])
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.compile import CompiledModule
from crowdrl.evaluation.rollout import crowd_env_of
from crowdrl.exploration.intrinsic import seeded_init
from crowdrl.models import make_q_actor
from crowdrl.models.predictor import make_predictor
from crowdrl.policies import OnlinePlanner
from crowdrl.training.config import PlanningConfig, TrainConfig
from crowdrl.training.facts import LIDAR_KEY, MASK_KEY, RunFacts, obs_keys
from crowdrl.training.predictor_learner import PredictorLearner

# what the learned crowd predictor trains on: world-frame states and the real next human states (one
# step later: the n-step transform moves only the observation keys), plus the humans' mask where the
# crowd size varies (the networks' observation keys hold it), as the planner reads it when acting
PREDICTOR_KEYS: list[NestedKey] = ["robot", "humans", ("next", "humans")]


class GreedyActing:
    """Act greedily on Q (TorchRL's ``QValueActor``): no model beside the network, nothing to learn or store.

    Args:
        encoder: the Q network's encoder name; entities: the network reads entity tokens (among obstacles);
        lidar: the network reads the lidar scan (``encoder.lidar``); compile: call the network through
            ``torch.compile`` (:class:`~crowdrl.compile.CompiledModule`).
    """

    predictor: torch.nn.Module | None = None

    def __init__(self, *, encoder: str, entities: bool, lidar: bool = False, compile: bool = False) -> None:
        self.encoder, self.entities, self.lidar, self.compile = encoder, entities, lidar, compile

    def actor(self, net: torch.nn.Module, env: EnvBase) -> TensorDictModuleBase:
        """The greedy actor of ``net`` for ``env``'s action spec, reading the humans' mask when ``env``'s crowd
        size varies (one network serves any crowd)."""
        if self.compile:
            net = CompiledModule(net, what="the acting Q network")
        return make_q_actor(self.encoder, env.action_spec, in_keys=obs_keys(crowd_env_of(env).config, self.entities, self.lidar),
                            net=net)

    def learners(self) -> list[AuxiliaryLearner]:
        """The models trained beside the Q network for this way of acting (none)."""
        return []

    def stored_keys(self) -> list[NestedKey]:
        """Replay-buffer keys its learners read beyond the transitions' (none)."""
        return []


class PlannedActing(GreedyActing):
    """Act through SG-D3QN's online planner (:class:`~crowdrl.policies.OnlinePlanner`): the top ``width``
    actions by Q re-scored by a ``depth``-step look-ahead through the crowd ``predictor``; a learned
    predictor is trained beside Q (:class:`~crowdrl.training.predictor_learner.PredictorLearner`, Adam at
    ``planning.lr``) on :data:`PREDICTOR_KEYS`.

    Args:
        section: the run's ``planning`` section; predictor: the crowd predictor (:func:`make_predictor_of`);
        reads_mask: the predictor's learner reads the humans' mask (the networks' observation keys hold it);
        gamma: the discount the look-ahead applies; learn: train the predictor (training) or only act with
        it (evaluation); compile_loss: the predictor's loss through ``torch.compile``; the rest as
        :class:`GreedyActing`.
    """

    def __init__(self, section: PlanningConfig, predictor: torch.nn.Module, *, encoder: str, entities: bool,
                 gamma: float, lidar: bool = False, reads_mask: bool = False, compile: bool = False, learn: bool = False,
                 compile_loss: bool = False) -> None:
        super().__init__(encoder=encoder, entities=entities, lidar=lidar, compile=compile)
        self.section, self.predictor, self.gamma = section, predictor, gamma
        self._learners: list[AuxiliaryLearner] = []
        if learn and any(True for _ in predictor.parameters()):  # const_vel has no weights
            optimizer = torch.optim.Adam(predictor.parameters(), lr=section.lr, fused=True)
            self._learners.append(PredictorLearner(predictor, optimizer, compile=compile_loss,
                                                   mask_key=MASK_KEY if reads_mask else None))

    def actor(self, net: torch.nn.Module, env: EnvBase) -> TensorDictModuleBase:
        crowd = crowd_env_of(env).config
        predictor = self.predictor
        if self.compile:
            net = CompiledModule(net, what="the acting Q network")
            predictor = CompiledModule(predictor, what="the planner's crowd predictor")
        p = self.section
        return OnlinePlanner(net, predictor, crowd, gamma=self.gamma, depth=p.depth, width=p.width,
                             mask_key=MASK_KEY if crowd.variable_crowd else None, entities=self.entities,
                             lidar_key=LIDAR_KEY if self.lidar else None, safety_horizon=p.safety_horizon,
                             progress_bias=p.progress_bias)

    def learners(self) -> list[AuxiliaryLearner]:
        """The learned predictor's learner while training (none for ``const_vel`` or when only acting)."""
        return list(self._learners)

    def stored_keys(self) -> list[NestedKey]:
        return list(PREDICTOR_KEYS) if self._learners else []


def make_predictor_of(section: PlanningConfig, facts: RunFacts) -> torch.nn.Module | None:
    """The planner's crowd predictor (``None`` without planning), initialised from a seed derived
    from the run seed: the global RNG, hence the Q network and everything after, is untouched."""
    if not section.enabled:
        return None
    with seeded_init(2_000_003 * (facts.seed + 1)):
        return make_predictor(section.predictor, facts.crowd.time_step).to(facts.device)


def make_acting(section: PlanningConfig, facts: RunFacts, *, train: TrainConfig, encoder: str,
                predictor: torch.nn.Module | None = None, learn: bool = False) -> GreedyActing:
    """The acting part of a run: :class:`PlannedActing` with ``section.enabled`` (its ``predictor``, a fresh
    seeded one when not given), else :class:`GreedyActing`. ``learn``: train the predictor (the trainer's part)."""
    if not section.enabled:
        return GreedyActing(encoder=encoder, entities=facts.entities, lidar=facts.lidar, compile=train.compile_acting)
    if predictor is None:
        predictor = make_predictor_of(section, facts)
    return PlannedActing(section, predictor, encoder=encoder, entities=facts.entities, lidar=facts.lidar, gamma=train.gamma,
                         reads_mask=MASK_KEY in facts.obs_keys, compile=train.compile_acting, learn=learn,
                         compile_loss=train.compile_loss)


__all__ = ["GreedyActing", "PREDICTOR_KEYS", "PlannedActing", "make_acting", "make_predictor_of"]

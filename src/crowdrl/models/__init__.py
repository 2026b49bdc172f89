"""Value networks: state encoders (selected by name from ``ENCODERS``) and the dueling Q head."""

from crowdrl.models.dueling import DuelingHead
from crowdrl.models.qnet import CrowdQNetwork, make_q_actor, make_q_network
from crowdrl.models.registry import ENCODERS, make_encoder, register_encoder
from crowdrl.models.sgd3qn import SGD3QNEncoder, SGD3QNEncoderNaive

__all__ = [
    "ENCODERS",
    "CrowdQNetwork",
    "DuelingHead",
    "SGD3QNEncoder",
    "SGD3QNEncoderNaive",
    "make_encoder",
    "make_q_actor",
    "make_q_network",
    "register_encoder",
]

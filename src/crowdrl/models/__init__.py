"""Value networks: state encoders (selected by name from ``ENCODERS``: ``sgd3qn``, ``sarl``,
``lstm_rl``, ``mp_rgl``) and the dueling Q head."""

from crowdrl.models.dueling import DuelingHead
from crowdrl.models.lstm_rl import LSTMRLEncoder
from crowdrl.models.mp_rgl import MPRGLEncoder
from crowdrl.models.qnet import CrowdQNetwork, make_q_actor, make_q_network
from crowdrl.models.registry import ENCODERS, make_encoder, register_encoder
from crowdrl.models.sarl import SARLEncoder
from crowdrl.models.sgd3qn import SGD3QNEncoder, SGD3QNEncoderNaive

__all__ = [
    "ENCODERS",
    "CrowdQNetwork",
    "DuelingHead",
    "LSTMRLEncoder",
    "MPRGLEncoder",
    "SARLEncoder",
    "SGD3QNEncoder",
    "SGD3QNEncoderNaive",
    "make_encoder",
    "make_q_actor",
    "make_q_network",
    "register_encoder",
]

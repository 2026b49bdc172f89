"""The paper's table over seeds (``crowdrl-reproduce``): the plan of runs and where their results live."""

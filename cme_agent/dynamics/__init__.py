"""Learning the conditional mean embedding E[phi(S') | s, a] ~ B psi(s, a)."""

from cme_agent.dynamics.cme import CMEDynamics
from cme_agent.dynamics.matching_pursuit import PursuitResult, matching_pursuit
from cme_agent.dynamics.sgd import sgd_step

__all__ = ["CMEDynamics", "PursuitResult", "matching_pursuit", "sgd_step"]

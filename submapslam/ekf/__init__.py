"""The stochastic map of the seed text (5.8.1): full-covariance EKF-SLAM with credibility."""

from .stochastic_map import CredibilityParams, MatchReport, StochasticMap, credibility

__all__ = ["CredibilityParams", "MatchReport", "StochasticMap", "credibility"]

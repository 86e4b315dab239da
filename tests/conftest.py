"""Shared test setup: the hypothesis profiles of the numerical-extremes properties (few examples by default; set
SPLATRIG_HYPOTHESIS_PROFILE=slow for many, see framework/testing/properties.py)."""

import framework.testing.properties  # noqa: F401  (registers and loads the profile)

"""Mitsuba integrator plugins of bdpt-drjit (registered by ``import bdpt_drjit``)."""

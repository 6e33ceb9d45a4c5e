"""Mitsuba plugins of mi_grg (installed as ``mi_grg.plugins``).

Each module defines its plugin class against the active variant and registers it at the
bottom, as Mitsuba's own Python integrators do. ``mi_grg.set_variant`` (re)loads them.
"""

"""The kinds of emitter that emitters.py has a model of, by Mitsuba class name.

emitters.py samples them and support.py refuses every other emitter; both read this
table, which imports nothing, so that emitters.py can import support.py's errors
without support.py importing emitters.py back (tests/test_layout.py)."""

AREA, POINT, SPOT, ENV, DIRECTIONAL, PROJECTOR = 0, 1, 2, 3, 4, 5
KINDS = {"AreaLight": AREA, "PointLight": POINT, "SpotLight": SPOT,
         "ConstantBackgroundEmitter": ENV, "EnvironmentMapEmitter": ENV,
         "DirectionalEmitter": DIRECTIONAL, "Projector": PROJECTOR,
         "SunskyEmitter": ENV}

"""The Blender add-on on the predicted skin (``likeness blender install``): a head as a mesh whose channels are
animatable properties, the skin from the ONNX predictor coloured by the strain guard, clips exported and imported
exactly, and a live link that streams the timeline to a running daemon.

Modules that need no Blender: :mod:`studio.blender.rig` (channels → pose → skin, colours, verdict),
:mod:`studio.blender.curves` (clip keys ↔ Blender keys, exactly), :mod:`studio.blender.recording` (recordings as
clips), :mod:`studio.blender.live` (the timestamped stream and the E-stop), :mod:`studio.blender.install` (the add-on
files). Modules that run inside Blender (``bpy``): :mod:`studio.blender.scene` (the head object and its update),
:mod:`studio.blender.anim` (actions ↔ clips), :mod:`studio.blender.addon` (operators, panels, handlers).
"""

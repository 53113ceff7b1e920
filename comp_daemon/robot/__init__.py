"""Robot descriptions (TOML, or a URDF: :mod:`comp_daemon.robot.urdf`) and the shipped presets:
:func:`comp_daemon.robot.description.load_robot` reads either; the types are in
:mod:`comp_daemon.robot.types`. Import from the module that defines a name; the package re-exports
nothing."""

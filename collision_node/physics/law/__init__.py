"""The contact law: impulses, friction, restitution and paths, written once."""

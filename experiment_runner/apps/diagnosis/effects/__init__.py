"""The effects a diagnosis can name: one class per effect, by family, and the shipped library.

Families: :mod:`.friction` (Coulomb level, viscous, position-dependent and asymmetric friction),
:mod:`.friction_laws` (Dahl, GMS, Stribeck, LuGre bristle damping, regularised Coulomb),
:mod:`.body` (mass, structural modes, FI compliance), :mod:`.drive` (force constant, delays),
:mod:`.forces` (ripple, offset, periodic force, isolator transient), :mod:`.stochastic` (drive
noise, quantization); what an effect declares and implements: :mod:`.base`. :data:`LIBRARY` is
every shipped effect, in the order candidates are proposed; ``nanostage diagnose --effects``
selects from it (:meth:`.library.Library.select`), ``Diagnosis(library=...)`` takes another.
"""
from .base import Case, Draw, Effect, Param, Parameter
from .body import FiCompliance, LocatedMode, Mass, Mode
from .drive import Delay, ForceConstant, FractionalDelay
from .forces import IsolatorTransient, Offset, PeriodicForce, Ripple
from .friction import Asymmetry, Coulomb, PositionFriction, Viscous
from .friction_laws import Dahl, Gms, LugreDamping, RegularizedCoulomb, Stribeck
from .library import Library
from .stochastic import NoiseLevel, Quantization

__all__ = ["LIBRARY", "SHIPPED", "Library", "Effect", "Param", "Parameter", "Case", "Draw"]

SHIPPED = (Dahl, Gms, Coulomb, Viscous, Stribeck, LugreDamping, RegularizedCoulomb, FiCompliance, PositionFriction,
           Ripple, Mode, LocatedMode, Delay, FractionalDelay, ForceConstant, Mass, Asymmetry, Offset, NoiseLevel,
           Quantization, PeriodicForce, IsolatorTransient)
"""Every shipped effect class, in the order candidates are proposed (a new effect is appended)."""

LIBRARY = Library(SHIPPED)
"""The default library: every shipped effect."""

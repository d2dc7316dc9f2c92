"""Physical constants of the Moon, SI units, each with its source."""

# Mean radius of the spherical Moon (paper Sec. 3.2, IAU/IAG mean radius 1737.4 km).
MOON_RADIUS_M = 1_737_400.0

# Gravitational parameter mu = 4902.8 km^3/s^2 (paper Sec. 3.3; DE430 gives 4902.800066).
MOON_GM_M3_S2 = 4.9028e12

# Rotation rate about +Z of MCI/MCMF (paper Sec. 3.2; one sidereal month, 27.3217 d).
MOON_ROTATION_RATE_RAD_S = 2.6617e-6

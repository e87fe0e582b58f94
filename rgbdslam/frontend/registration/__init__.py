"""Registration strategies: matched 3-D points -> rigid pose + inliers + information.

One interface (:class:`~rgbdslam.frontend.registration.base.Registration`, ``fit(S, D)``
-> :class:`~rgbdslam.frontend.registration.base.RigidFit`), one class per strategy, chosen by
``registration.method`` through :func:`get_registration`. A new strategy is a subclass in its
own module here, listed in :data:`STRATEGIES` (and its name in the ``method`` choices of
:class:`rgbdslam.frontend.config.RegistrationConfig`); the front end and the loop closer use whatever
this factory returns.
"""

from __future__ import annotations

from rgbdslam.errors import ConfigError
from rgbdslam.frontend.config import RegistrationConfig
from rgbdslam.frontend.registration.base import Registration, RigidFit, fit_information, point_information
from rgbdslam.frontend.registration.islam import IslamRegistration
from rgbdslam.frontend.registration.isvd import IsvdRegistration
from rgbdslam.frontend.registration.ransac import RansacRegistration

STRATEGIES: dict[str, type[Registration]] = {
    cls.name: cls for cls in (RansacRegistration, IsvdRegistration, IslamRegistration)
}


def get_registration(rc: RegistrationConfig) -> Registration:
    """The strategy named by ``rc.method``, built from the ``registration`` section."""
    try:
        return STRATEGIES[rc.method](rc)
    except KeyError:
        raise ConfigError(f"config key 'registration.method' must be one of {', '.join(STRATEGIES)}; "
                          f"got {rc.method!r}") from None


__all__ = ["Registration", "RigidFit", "STRATEGIES", "fit_information", "get_registration", "point_information"]

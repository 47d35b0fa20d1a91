"""The contracts that frontends, services and the backend hand each other: the contributor contract
(:mod:`.contributor`: what a service may ask of a frontend, the global BA hand-over) and the
factor-plugin contract (:mod:`.plugins`). They sit below both frontends and services, so that the
two are peers under the system."""

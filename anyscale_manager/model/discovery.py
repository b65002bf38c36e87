"""Where a deployment's discovery servers are (``discovery.mode: server``): one per scale, on
the scale's host, at ``discovery.port`` + ``DOMAIN_STRIDE`` x the ROS domain + the scale's index
in the file. Every process of the deployment is a client of all of them (ROS_DISCOVERY_SERVER
lists them by index: Fast DDS takes the i-th entry for the server with id i), so two processes
of one scale still find each other through their own scale's server while a link is cut.

The domain is in the port because a discovery server ignores DDS domains: two robots of a fleet
(each its own domain) whose files name the same shared server scale would otherwise be clients
of one server there, and their topics would match across robots. Pure: resolving host names is
the caller's (``resolve``: an address, or '' when the name cannot be resolved now; the entry is
then left empty, as Fast DDS drops the whole list over one name it cannot resolve).
"""

from typing import Callable, Dict, Optional

from .types import SERVER, Deployment

ENV_SERVERS = 'ROS_DISCOVERY_SERVER'
ENV_SUPER_CLIENT = 'ROS_SUPER_CLIENT'
ENV_DOMAIN = 'ROS_DOMAIN_ID'
DOMAIN_STRIDE = 16          # the most scales a deployment may have under discovery.mode server
MAX_DOMAIN = 232


def uses_servers(deployment: Deployment) -> bool:
    return deployment.discovery.mode == SERVER


def domain_of(environ) -> int:
    """The ROS domain of an environment (0 when unset or not a domain)."""
    try:
        domain = int(environ.get(ENV_DOMAIN, '0') or '0')
    except ValueError:
        return 0
    return domain if 0 <= domain <= MAX_DOMAIN else 0


def server_id(deployment: Deployment, scale: str) -> int:
    return deployment.scale_names.index(scale)


def server_port(deployment: Deployment, scale: str, domain: int) -> int:
    return deployment.discovery.port + DOMAIN_STRIDE * domain + server_id(deployment, scale)


def server_list(deployment: Deployment, domain: int,
                resolve: Callable[[str], Optional[str]] = str) -> str:
    """ROS_DISCOVERY_SERVER's value: every scale's server, in the file's order of scales (an
    empty entry for a host ``resolve`` cannot name)."""
    out = []
    for s in deployment.scales:
        address = resolve(s.host)
        out.append(f'{address}:{server_port(deployment, s.name, domain)}' if address else '')
    return ';'.join(out)


def client_environment(deployment: Deployment, domain: int,
                       resolve: Callable[[str], Optional[str]] = str) -> Dict[str, str]:
    """What a process of the deployment needs in its environment to discover the others: none
    under multicast."""
    if not uses_servers(deployment):
        return {}
    return {ENV_SERVERS: server_list(deployment, domain, resolve)}

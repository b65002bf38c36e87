"""Where a deployment's discovery servers are (``discovery.mode: server``): one per scale, on
the scale's host, at ``discovery.port`` + the scale's index in the file. Every process of the
deployment is a client of all of them (ROS_DISCOVERY_SERVER lists them by index: Fast DDS takes
the i-th entry for the server with id i), so two processes of one scale still find each other
through their own scale's server while a link is cut. Pure: resolving host names is the
caller's (``resolve``)."""

from typing import Callable, Dict

from .types import SERVER, Deployment

ENV_SERVERS = 'ROS_DISCOVERY_SERVER'
ENV_SUPER_CLIENT = 'ROS_SUPER_CLIENT'


def uses_servers(deployment: Deployment) -> bool:
    return deployment.discovery.mode == SERVER


def server_id(deployment: Deployment, scale: str) -> int:
    return deployment.scale_names.index(scale)


def server_port(deployment: Deployment, scale: str) -> int:
    return deployment.discovery.port + server_id(deployment, scale)


def server_list(deployment: Deployment, resolve: Callable[[str], str] = str) -> str:
    """ROS_DISCOVERY_SERVER's value: every scale's server, in the file's order of scales."""
    return ';'.join(f'{resolve(s.host)}:{server_port(deployment, s.name)}'
                    for s in deployment.scales)


def client_environment(deployment: Deployment,
                       resolve: Callable[[str], str] = str) -> Dict[str, str]:
    """What a process of the deployment needs in its environment to discover the others: none
    under multicast."""
    if not uses_servers(deployment):
        return {}
    return {ENV_SERVERS: server_list(deployment, resolve)}

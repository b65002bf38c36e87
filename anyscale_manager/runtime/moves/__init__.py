"""The migration policy's moves, one module each (runtime/policy.py runs them in turn).

``pending``: a move the agents do not apply in time is undone. ``failover``: a crashed serving
copy hands over to a standby. ``relocate``: the nodes of a lost scale go where a live agent can
run them. ``back``: Algorithm 1's violation branch. ``out``: its else branch, one node (or
coresidence group) out of the master. ``rebalance``: to a more powerful remote scale when the
cost function gains enough. ``next_best``: where a node that must leave a scale goes.
``state``: what they share (the policy's memory, one step's inputs); ``units``: which nodes
move together, and from where.
"""

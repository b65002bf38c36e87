"""The ICAR 2015 test-bed on one machine: namespaces, a shaped link, CPU quotas, a harness."""

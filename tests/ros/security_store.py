"""The enclave the security tests' keystore (`store`, tests/ros/conftest.py) is made with."""

ENCLAVE = "/robot1/rcan_bridge"

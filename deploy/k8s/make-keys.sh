#!/bin/sh
# Issue the key files the Kubernetes manifests mount (deploy/k8s/keys/, git-ignored), with the
# project's own command, then: kubectl apply -k deploy/k8s
# keys/operator.key derives every credential: keep it with the operator (it is in no Secret).
set -eu
here=$(dirname "$0")
recslam keys new --dir "$here/keys" --edge edge-site-a --robot robot0 --robot robot1 --robot robot2

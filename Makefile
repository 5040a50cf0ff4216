# The two commands of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
VENV := .venv/bin
SPEC ?= examples/pick-and-place.yml
export ANSIBLE_CONFIG := $(CURDIR)/ansible.cfg
export PATH := $(CURDIR)/.venv/bin:$(PATH)

# Versions of the local control plane: one place, the local_cluster role's defaults.
version = $(shell sed -n 's/^local_cluster_$(1)_version: *//p' roles/local_cluster/defaults/main.yml)
BUILD_ENV := KUBERNETES_VERSION=$(call version,kubernetes) ETCD_VERSION=$(call version,etcd) KWOK_VERSION=$(call version,kwok) \
	COREDNS_VERSION=$(call version,coredns)
REAL := inventories/real-pods
REAL_KUBECONFIG = $${KUBEROS_CACHE_DIR:-$$HOME/.cache/kuberos}/cluster-real/kubeconfig

.PHONY: setup binaries cluster cluster-stop demo demo-real demo-real-stop bench-connectivity bench-discovery bench-discovery-traffic bench-real-pods bench-site bench-platform-pods bench-images bench-dashboard bench-scaling controller controller-stop status test test-full site-upgrade lint sanity unit molecule schema bench bench-deploy bench-controller bench-rollout bench-pool sim evaluate clean

setup:
	@scripts/setup.sh

## Build the control plane from the Go module proxy, once (cached by version outside the repo); WITH_NODES=1 adds
## kubelet, kube-proxy and CoreDNS for real nodes.
binaries: setup
	@$(BUILD_ENV) SKIP_KUBECTL=$(if $(WITH_KUBECTL),0,1) SKIP_KUBEADM=$(if $(WITH_KUBEADM),0,1) SKIP_NODES=$(if $(WITH_NODES),0,1) \
	  roles/local_cluster/files/build-binaries.sh

## Start the local cluster (a real control plane, kwok nodes from inventories/local).
cluster: binaries
	$(VENV)/ansible-playbook playbooks/local_cluster.yml -i inventories/local

cluster-stop: setup controller-stop
	$(VENV)/ansible-playbook playbooks/local_cluster.yml -i inventories/local -e local_cluster_state=stopped

## Deploy the example application to the embedded default site (inventories/local), and start the controller.
demo: cluster
	$(VENV)/ansible-playbook playbooks/deploy.yml -i inventories/local -e rosdeployment_file=$(SPEC)
	$(VENV)/ansible-playbook playbooks/controller.yml -i inventories/local

## The example application as real pods on real kubelets (inventories/real-pods: a robot, two edge servers and a
## cloud VM as network-namespace nodes on this machine; as root; docs/real-nodes.md), the controller, and the
## robot's simulated hardware until it has done CYCLES pick cycles. The programs and the images are built before
## Ansible starts, where their builds print progress lines.
demo-real: setup
	$(MAKE) binaries WITH_NODES=1
	PYTHONPATH=$(CURDIR)/.collections $(VENV)/python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images build
	$(VENV)/ansible-playbook playbooks/local_cluster.yml -i $(REAL)
	$(VENV)/ansible-playbook playbooks/deploy.yml -i $(REAL) -e rosdeployment_file=$(SPEC)
	$(VENV)/ansible-playbook playbooks/controller.yml -i $(REAL)
	PYTHONPATH=$(CURDIR)/sim:$(CURDIR)/.collections $(VENV)/python -m kuberos_sim.real_pods --kubeconfig $(REAL_KUBECONFIG) \
	  --robots robot-1 --cycles $(CYCLES)

## Stop the real-pod fleet and leave the host as it was (add STATE=absent to remove its state and images too).
demo-real-stop: setup
	$(VENV)/ansible-playbook playbooks/controller.yml -i $(REAL) -e controller_state=stopped
	$(VENV)/ansible-playbook playbooks/local_cluster.yml -i $(REAL) -e local_cluster_state=$(or $(STATE),stopped)

## The controller: moves modules off failed nodes, failing pods and slow links (docs/controller.md).
controller: setup
	$(VENV)/ansible-playbook playbooks/controller.yml -i inventories/local

controller-stop: setup
	$(VENV)/ansible-playbook playbooks/controller.yml -i inventories/local -e controller_state=stopped

## Where every module of every robot runs, as the controller reports it.
status: setup
	$(VENV)/ansible-playbook playbooks/status.yml -i inventories/local

## Lint and every test (the cluster tests start their own control plane; the cluster setup roles' tests need kubeadm,
## and Cilium's programs, the lab's pod network, built from Cilium's Go module).
## The collection's images and the lab machines' Debian root are built beside the Go programs (downloads and disk
## more than CPU; their log: $(PREBUILD_LOG)); a build that fails there fails again in the test that needs it, which
## says why. Then pytest in two lanes side by side (docs/testing.md), while the images of the lab machines' cluster
## (kubeadm's and Cilium's, from the Go programs) are built beside the first tests (the site chain, which needs them,
## comes later in its lane and waits for the build if it is not done).
## make test leaves out the site chain's upgrade (make site-upgrade) and the tests marked full: a second proof of what
## it proves elsewhere (docs/testing.md), so that CI's 90 minutes hold the rest. make test-full runs those too.
TEST_MARKERS := not upgrade and not full
PREBUILD_LOG := $${KUBEROS_CACHE_DIR:-$$HOME/.cache/kuberos}/prebuild.log
test: setup
	@mkdir -p "$${KUBEROS_CACHE_DIR:-$$HOME/.cache/kuberos}"; \
	{ PYTHONPATH=$(CURDIR)/.collections $(VENV)/python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images build \
	  && PYTHONPATH=$(CURDIR)/.collections $(VENV)/python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.machines root; \
	} >"$(PREBUILD_LOG)" 2>&1 & prebuild=$$!; \
	$(MAKE) binaries WITH_KUBEADM=1 WITH_NODES=1 \
	  && roles/local_cluster/files/build-cilium.sh \
	  && scripts/operator-crds.sh >/dev/null && scripts/calico-manifest.sh >/dev/null \
	  && roles/local_cluster/files/build-kube-score.sh; built=$$?; \
	wait $$prebuild || echo "make test: the images or the machines' root did not build here ($(PREBUILD_LOG)); the tests that need them build them again"; \
	[ $$built -eq 0 ] || exit 1; \
	PYTHONPATH=$(CURDIR)/.collections $(VENV)/python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.machines \
	  site-images >>"$(PREBUILD_LOG)" 2>&1 & images=$$!; \
	$(VENV)/python -m pytest -n 2 --dist loadgroup -m "$(TEST_MARKERS)"; tested=$$?; \
	wait $$images || echo "make test: the lab machines' images did not build beside the tests ($(PREBUILD_LOG))"; \
	exit $$tested

## make test with the tests marked full (about 10 more minutes on two cores).
test-full:
	$(MAKE) test TEST_MARKERS="not upgrade"

## The site chain with the Kubernetes upgrade (tests/site, as root, 40 to 50 minutes): the site built at UPGRADE_FROM,
## upgraded to the pinned release with upgrade.yml while the app runs, then the chain's other steps at the new release.
## make test leaves the upgrade out: CI's 90 minutes cannot hold it yet (docs/testing.md).
UPGRADE_FROM := v1.33.13
site-upgrade: setup
	$(MAKE) binaries WITH_KUBEADM=1 WITH_NODES=1
	@$(BUILD_ENV) KUBERNETES_VERSION=$(UPGRADE_FROM) SKIP_KUBECTL=1 SKIP_KUBEADM=0 SKIP_NODES=0 roles/local_cluster/files/build-binaries.sh
	@roles/local_cluster/files/build-cilium.sh
	KUBEROS_SITE_KUBERNETES_VERSION=$(UPGRADE_FROM) $(VENV)/python -m pytest tests/site

unit: setup
	$(VENV)/python -m pytest tests/unit

## Every molecule scenario run whole (as root), also those on lab machines that `make test` only syntax-checks because
## the site chain runs their roles (kubeadm_init, kubeadm_join, cilium; docs/testing.md). S=NAME runs one.
molecule: setup
	$(MAKE) binaries WITH_KUBEADM=1 WITH_NODES=1
	@roles/local_cluster/files/build-cilium.sh
	KUBEROS_MACHINE_SCENARIOS=1 $(VENV)/python -m pytest tests/molecule $(if $(S),-k "$(S)")

## Lint as the ecosystem does: ruff, yamllint, ansible-lint (production profile), ansible-test sanity on the built
## collection and the tarball's contents (tests/lint; docs/testing.md). Set-up first: it works on a fresh clone.
lint: setup
	$(VENV)/python -m pytest tests/lint

## ansible-test sanity alone (scripts/sanity.sh); TEST=pylint runs one of its tests.
sanity: setup
	scripts/sanity.sh $(if $(TEST),--test $(TEST))

## Regenerate docs/rosdeployment.schema.json from the schema in the code.
schema: setup
	$(VENV)/python scripts/write_schema.py

## Scheduler benchmark; results go to bench/RESULTS.md by hand, with machine and date.
bench: setup
	$(VENV)/python bench/bench_scheduler.py

## Deploy benchmark against the local control plane (needs kubectl for the side-by-side ratio).
bench-deploy:
	$(MAKE) binaries WITH_KUBECTL=1
	$(VENV)/python bench/bench_deploy.py

## Controller failover benchmark: node NotReady -> affected modules Running elsewhere (p50/p95).
bench-controller: binaries
	$(VENV)/python bench/bench_controller.py

## Rollout benchmark: 100 robots, one module upgraded in waves of 10, and a broken version stopped at the canary.
bench-rollout: binaries
	cd bench && ../$(VENV)/python bench_rollout.py --json results/rollout.json

## The robot pool's pass: a reserved robot freed and given back with 1 and 4 production deployments on it.
bench-pool: binaries
	$(VENV)/python bench/bench_pool_pass.py --json bench/results/pool_pass.json

## Connectivity on real nodes: a robot cut off longer than the eviction delay (its pods, moves, rematch after
## reconnecting), and edge kubelets stopped in turn (time until their modules run elsewhere; docs/connectivity.md).
bench-connectivity:
	$(MAKE) binaries WITH_NODES=1
	$(VENV)/python bench/bench_connectivity.py --json bench/results/connectivity.json

## Discovery under faults (as root): rclpy in network namespaces, a robot cut off, discovery servers restarted
## (tests/discovery_faults.py; docs/connectivity.md).
bench-discovery: setup
	$(VENV)/python bench/bench_discovery.py --repeat 3 --json bench/results/discovery.json \
	  --connectivity bench/results/connectivity.json

## Discovery traffic: bytes and packets for 10, 50 and 200 participants, multicast against discovery servers (as root).
bench-discovery-traffic: setup
	$(VENV)/python bench/bench_discovery_traffic.py --json bench/results/discovery_traffic.json

## Real nodes: image build, cold and warm start, deploy to all pods Running, pick cycles against the netns runtime.
bench-real-pods:
	$(MAKE) binaries WITH_NODES=1
	cd bench && ../$(VENV)/python bench_real_pods.py --cold-images --json results/real-pods.json

## Site benchmark (as root): the sample site on seven lab machines from bare machines to a running fleet, and back
## (docs/cluster-setup.md).
bench-site: setup
	$(MAKE) binaries WITH_KUBEADM=1 WITH_NODES=1
	@roles/local_cluster/files/build-cilium.sh
	$(VENV)/python bench/bench_site.py --json bench/results/site.json

## Images benchmark (as root): every image built cold and warm, rebuilt for the same digests, pushed to the lab
## registry and pulled cold by digest into fresh containerds (docs/real-nodes.md).
bench-images: setup
	cd bench && ../$(VENV)/python bench_images.py --json results/images.json

## The platform as pods (as root): the in-cluster controller's takeover over 20 killed leaders (p95), and the bridge's
## added latency as pods between this cluster and a second cluster of real nodes (bench/results/images.json).
bench-platform-pods: setup
	$(MAKE) binaries WITH_NODES=1
	cd bench && ../$(VENV)/python bench_platform_pods.py --json results/images.json

## Dashboard and /metrics benchmark: 1,000 robots; first paint in Chromium, view builds, scrape cost (docs/dashboard.md).
bench-dashboard: binaries
	cd bench && ../$(VENV)/python bench_dashboard.py --robots 1000

## The pick-and-place fleet for real on this machine: one strategy, one fleet size (as root; docs/simulation.md).
##   make sim STRATEGY=edge-shared ROBOTS=4 RATE=12 CYCLES=3
STRATEGY ?= cloud
ROBOTS ?= 1
RATE ?= 12
CYCLES ?= 3
sim: setup
	PYTHONPATH=$(CURDIR)/sim:$(CURDIR)/.collections $(VENV)/python -m kuberos_sim.evaluate --strategies $(STRATEGY) \
	  --robots $(ROBOTS) --rates $(RATE) --cycles $(CYCLES) --out sim/out/$(STRATEGY)-$(ROBOTS)

## The whole evaluation (strategies x fleet sizes x rates x 3 seeds) into sim/results/: table with the seeds' spread,
## plots, command, commit, machine (about 2 hours on 2 cores).
SEEDS ?= 1-3
evaluate: setup
	PYTHONPATH=$(CURDIR)/sim:$(CURDIR)/.collections $(VENV)/python -m kuberos_sim.evaluate --seeds $(SEEDS) --out sim/results

## Scaling: the edge planner scaled on its queue against dedicated and fixed shared planners (as root; docs/scaling.md).
bench-scaling: setup
	$(VENV)/python bench/bench_scaling.py --json bench/results/scaling.json --plot docs/images/scaling-instances.png

clean:
	rm -rf rendered bench/out sim/out .pytest_cache .hypothesis

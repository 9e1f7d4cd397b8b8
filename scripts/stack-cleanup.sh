# Sourced by scripts/compose-smoke.sh (and usable by hand: `source scripts/stack-cleanup.sh;
# remove_stack curlnav`). `docker stack rm` keeps a stack's named volumes (curlnav_learner,
# curlnav_replay, curlnav_scheduler): a later `docker stack deploy` would start from their old
# checkpoint, replay log and curriculum state. remove_stack removes the stack, waits until its
# containers are gone (a volume in use cannot be removed), then removes its volumes.

# remove_stack STACK [SECONDS]: 0 when the stack and its volumes are gone, 1 when its containers
# outlived SECONDS (default 120).
remove_stack() {
  local stack=${1:-curlnav} limit=${2:-120}
  local label="label=com.docker.stack.namespace=$stack" deadline=$(( $(date +%s) + ${2:-120} ))
  docker stack rm "$stack" >/dev/null 2>&1 || true
  while [ -n "$(docker ps -aq --filter "$label" 2>/dev/null)" ]; do
    if [ "$(date +%s)" -ge "$deadline" ]; then
      echo "remove_stack: containers of stack $stack still there after ${limit}s; its volumes are kept:"
      docker ps -a --filter "$label" || true
      return 1
    fi
    sleep 2
  done
  local volume
  for volume in $( { printf '%s\n' "${stack}_learner" "${stack}_replay" "${stack}_scheduler";
                     docker volume ls -q --filter "$label" 2>/dev/null || true; } | sort -u); do
    if docker volume inspect "$volume" >/dev/null 2>&1; then
      docker volume rm "$volume" >/dev/null
      echo "removed volume $volume"
    fi
  done
}

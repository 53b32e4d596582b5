# Shared by the paper recipes (cli/table1.sh, cli/table2.sh, cli/message_size.sh, cli/foundation.sh): resumable
# runs, and the PARTS option.
#
#   train_once DIR [mpsim train arguments...]
#     DIR/summary.json exists          → the run finished: kept, not rerun
#     DIR/checkpoints/last.ckpt exists → the run was interrupted: resumed with resume=DIR (same arguments)
#     otherwise                        → a fresh run in DIR
#     DEVICE=cpu|cuda|auto (unset: the run's own or mpsim's default) is added as device=$DEVICE to both, so a
#     run begun on a GPU machine resumes on a CPU with the recipe itself (a resumed run may change its device).
#     Each run holds the lock DIR.lock while it trains, so two recipes (or a recipe and a hand-started
#     train_once) that reach the same run never train it twice at once: the second waits, then keeps or
#     resumes what the first left.
#   parallel JOBS < lines              → runs each line (a train_once call) with up to JOBS at once
#   check_choices RECIPE NAME VALUE... → stops (exit 2, one message) if the list in $NAME (commas or spaces)
#                                        holds a value not in VALUE..., before anything trains: a typo must
#                                        not cost the hours the parts before it take
#   check_parts RECIPE PART...         → check_choices RECIPE PARTS PART...
#   check_counts RECIPE NAME...        → stops (exit 2, one message) if a variable NAME (a number, or a list with
#                                        commas or spaces) holds anything but positive integers: sizes and epochs
#
# So an interrupted recipe is continued by running it again with the same settings; FRESH=1 starts over.
train_once() {
  local dir=${1%/}; shift
  local lock
  mkdir -p "$(dirname "$dir")"
  exec {lock}>"$dir.lock"
  if ! flock -n "$lock"; then
    echo "waiting: $dir is being trained by another process"
    flock "$lock"
  fi
  if [ -f "$dir/summary.json" ]; then
    echo "kept (finished): $dir"
  elif [ -f "$dir/checkpoints/last.ckpt" ]; then
    echo "resuming: $dir"
    mpsim train "$@" ${DEVICE:+"device=$DEVICE"} resume="$dir"
  else
    mpsim train "$@" ${DEVICE:+"device=$DEVICE"} hydra.run.dir="$dir"
  fi
  local rc=$?
  exec {lock}>&-
  return $rc
}

parallel() {
  local here; here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
  xargs -P "$1" -I{} bash -c "set -euo pipefail; source '$here/lib.sh'; {}"
}

check_choices() {  # RECIPE NAME ALLOWED...: the list in $NAME (commas or spaces) may hold only ALLOWED values
  local recipe=$1 name=$2 value; shift 2
  printf -v "$name" '%s' "${!name//,/ }"
  for value in ${!name}; do
    if [[ " $* " != *" $value "* ]]; then
      echo "$recipe: unknown value '$value' in $name (known: $*)" >&2
      exit 2
    fi
  done
}

check_parts() { local recipe=$1; shift; check_choices "$recipe" PARTS "$@"; }

check_counts() {  # RECIPE NAME...: each $NAME holds positive integers only (a typo must not surface hours in)
  local recipe=$1 name value; shift
  for name in "$@"; do
    for value in ${!name//,/ }; do
      [[ $value =~ ^[1-9][0-9]*$ ]] || { echo "$recipe: $name='${!name}' is not a positive integer" >&2; exit 2; }
    done
  done
}

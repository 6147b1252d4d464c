#!/usr/bin/env bash
# A stream of transport orders for `agv serve --simulate warehouse-20` (docs/service.md).
#
#   docs/examples/post_orders.sh [URL] [KEY_FILE] [COUNT] [PER_SECOND]
#
# Posts COUNT orders (default 100) at PER_SECOND (default 2) with curl: each has a fresh
# client-chosen id, a pickup at one of warehouse-20's shelf faces and a drop-off at one of its
# stations. A post that fails (the service restarting, say) is retried with the same id, which
# the service counts once. Needs bash and curl only.
set -euo pipefail
URL=${1:-http://127.0.0.1:8000}
KEY_FILE=${2:-api.key}
COUNT=${3:-100}
RATE=${4:-2}
KEY=$(tr -d '[:space:]' < "$KEY_FILE")
PICKUPS=(1.90,1.80 2.50,1.80 3.10,1.80 3.70,1.80 4.30,1.80 4.90,1.80 5.50,1.80 6.10,1.80
         1.90,2.80 2.50,2.80 3.10,2.80 3.70,2.80 4.30,2.80 4.90,2.80 5.50,2.80 6.10,2.80
         1.90,3.20 2.50,3.20 3.10,3.20 3.70,3.20 4.30,3.20 4.90,3.20 5.50,3.20 6.10,3.20
         1.90,4.20 2.50,4.20 3.10,4.20 3.70,4.20 4.30,4.20 4.90,4.20 5.50,4.20 6.10,4.20
         1.90,4.60 2.50,4.60 3.10,4.60 3.70,4.60 4.30,4.60 4.90,4.60 5.50,4.60 6.10,4.60
         1.90,5.60 2.50,5.60 3.10,5.60 3.70,5.60 4.30,5.60 4.90,5.60 5.50,5.60 6.10,5.60)
STATIONS=(0.40,0.40 0.40,1.20 0.40,2.00 0.40,2.80 0.40,3.60 0.40,4.40 0.40,5.20)
RUN=demo-$(date +%s)
PAUSE=$(awk "BEGIN { print 1 / $RATE }")
for ((k = 0; k < COUNT; k++)); do
  P=${PICKUPS[RANDOM % ${#PICKUPS[@]}]}
  D=${STATIONS[RANDOM % ${#STATIONS[@]}]}
  BODY="{\"id\": \"$RUN-$k\", \"pickup\": [$P], \"dropoff\": [$D], \"priority\": $((RANDOM % 3))}"
  for try in 1 2 3 4 5 6 7 8 9 10; do
    CODE=$(curl -s -o /dev/null -w '%{http_code}' -X POST "$URL/v1/orders" \
           -H "Authorization: Bearer $KEY" -H 'Content-Type: application/json' -d "$BODY" \
           || true)
    case $CODE in
      200|201) break ;;
      4??) echo "order $RUN-$k refused: HTTP $CODE" >&2; break ;;
      *) sleep 1 ;;
    esac
  done
  echo "$RUN-$k $CODE"
  sleep "$PAUSE"
done
curl -s -H "Authorization: Bearer $KEY" "$URL/v1/plan" | \
  sed -e 's/.*"stats":\({[^}]*}\).*/\1/'

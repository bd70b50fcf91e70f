/* The thread fan-out of every parallel kernel (gs_common.h). Plain pthreads, started per
 * call: a kernel call is milliseconds or more, thread start-up tens of microseconds, and
 * no pool survives into a forked child (process pools of the fitting fork). */
#include <pthread.h>
#include <stdlib.h>

#include "gs_common.h"

typedef struct {
    gs_task_fn fn;
    void *ctx;
    int64_t ntasks;
    int64_t next; /* shared counter, atomic */
} gs_fanout;

static void *gs_worker(void *arg)
{
    gs_fanout *f = (gs_fanout *)arg;
    for (;;) {
        int64_t task = __atomic_fetch_add(&f->next, 1, __ATOMIC_RELAXED);
        if (task >= f->ntasks)
            break;
        f->fn(f->ctx, task);
    }
    return NULL;
}

void gs_parallel_for(int nthreads, int64_t ntasks, gs_task_fn fn, void *ctx)
{
    gs_fanout f = {fn, ctx, ntasks, 0};
    if (nthreads > ntasks)
        nthreads = (int)ntasks;
    if (nthreads <= 1) {
        for (int64_t task = 0; task < ntasks; ++task)
            fn(ctx, task);
        return;
    }
    pthread_t *ids = malloc(sizeof(pthread_t) * (size_t)(nthreads - 1));
    int started = 0;
    if (ids != NULL) {
        for (; started < nthreads - 1; ++started)
            if (pthread_create(&ids[started], NULL, gs_worker, &f) != 0)
                break; /* fewer threads: the counter still hands out every task */
    }
    gs_worker(&f);
    for (int i = 0; i < started; ++i)
        pthread_join(ids[i], NULL);
    free(ids);
}

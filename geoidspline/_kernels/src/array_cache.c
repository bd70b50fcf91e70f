/* A caching allocator for numpy's array data (numpy's PyDataMem handler, NEP 49), used
 * while a band is fitted (geoidspline/_kernels/array_cache.py installs it).
 *
 * Why: a band's fit makes many large temporary arrays. glibc maps each large one
 * fresh and unmaps it when freed, so the kernel zeroes every page again on first touch
 * (much of the fit's system time: benchmarks/README.md). Here a freed large block is kept and handed to the
 * next request of its size class, so its pages are reused as they are.
 *
 * A request that finds no kept block of its class takes the kept block nearest its size
 * and remaps it to the size asked (blocks from 32 MiB on are mapped here, mremap moves
 * pages without copying them): only the pages it grows by are new. A band's arrays grow
 * and shrink with its lattice, so most sizes are new to the cache.
 *
 * Bounded: the blocks kept never raise the allocator's resident bytes (in use + kept)
 * above the highest bytes in use seen since the cache was opened; a request that finds
 * no kept block of its class first releases kept blocks, oldest first, until it fits
 * under that mark. Closing the last user of the cache releases every kept block.
 *
 * Plain C, no Python headers: the handler's layout below is numpy's PyDataMem_Handler
 * (version 1, numpy/ndarraytypes.h), which numpy keeps stable. Every block carries a
 * header with its capacity, so blocks allocated while the cache is open may be freed
 * after it closes (numpy frees an array through the handler that allocated it). */
#define _GNU_SOURCE /* mremap */
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>

#include "gs_common.h"

typedef struct {
    void *ctx;
    void *(*malloc)(void *ctx, size_t size);
    void *(*calloc)(void *ctx, size_t nelem, size_t elsize);
    void *(*realloc)(void *ctx, void *ptr, size_t new_size);
    void (*free)(void *ctx, void *ptr, size_t size);
} gs_data_allocator;

typedef struct {
    char name[127];
    uint8_t version;
    gs_data_allocator allocator;
} gs_data_handler;

/* 64 bytes keep numpy's alignment (it needs 16) and a cache line. */
#define HEADER_BYTES 64
/* Blocks from this size on are kept: below it glibc reuses its heap anyway. */
#define LARGE_BYTES ((size_t)1 << 20)
/* Large capacities are rounded up to this (a huge page), so near sizes share a class. */
#define CLASS_BYTES ((size_t)1 << 21)
/* As numpy's own allocator: transparent huge pages for blocks from 4 MiB on. */
#define HUGEPAGE_BYTES ((size_t)1 << 22)
/* Blocks from this size on are mapped here (mmap, mremap): glibc maps them anyway. */
#define MAP_BYTES ((size_t)1 << 25)
#define MAX_KEPT 512
/* A request may take a kept block up to 1/SLACK_OVER larger than its class. */
#define SLACK_OVER 4

typedef struct {
    size_t capacity; /* data bytes after the header */
    uint64_t serial; /* order of keeping: the oldest is released first */
    void *base;
} kept_block;

static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;
static int64_t users;          /* open scopes; kept blocks only while > 0 */
static size_t in_use_bytes;    /* large blocks handed out and not freed */
static size_t kept_bytes;      /* large blocks kept for reuse */
static size_t high_bytes;      /* highest in_use_bytes since the cache opened */
static uint64_t next_serial;
static int64_t nkept;
static kept_block kept[MAX_KEPT];
static int64_t reused_count, fresh_count, fresh_bytes;

static size_t capacity_for(size_t size)
{
    if (size < LARGE_BYTES)
        return size;
    size_t total = size + HEADER_BYTES;
    return (total + CLASS_BYTES - 1) / CLASS_BYTES * CLASS_BYTES - HEADER_BYTES;
}

/* A new block of `total` bytes (zeroed when mapped; `zeroed` asks it of the heap too). */
static void *block_new(size_t total, int zeroed)
{
    if (total < MAP_BYTES)
        return zeroed ? calloc(1, total) : malloc(total);
    void *base = mmap(NULL, total, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (base == MAP_FAILED)
        return NULL;
    if (total >= HUGEPAGE_BYTES)
        madvise(base, total, MADV_HUGEPAGE);
    return base;
}

static void block_free(void *base, size_t total)
{
    if (total < MAP_BYTES)
        free(base);
    else
        munmap(base, total);
}

/* A mapped block of `old_total` bytes remapped to `new_total` (both mapped sizes): its
 * pages kept up to the smaller size, the rest new (zero). NULL if it cannot be. */
static void *block_resize(void *base, size_t old_total, size_t new_total)
{
    void *moved = mremap(base, old_total, new_total, MREMAP_MAYMOVE);
    if (moved == MAP_FAILED)
        return NULL;
    if (new_total > old_total && new_total >= HUGEPAGE_BYTES)
        madvise(moved, new_total, MADV_HUGEPAGE);
    return moved;
}

static void *data_of(void *base) { return (char *)base + HEADER_BYTES; }
static void *base_of(void *data) { return (char *)data - HEADER_BYTES; }

static void release_kept(int64_t i)
{
    kept_bytes -= kept[i].capacity;
    block_free(kept[i].base, HEADER_BYTES + kept[i].capacity);
    kept[i] = kept[--nkept];
}

/* Take kept block i out of the kept set (the lock is held; its capacity in *taken). */
static void *take_at(int64_t i, size_t *taken)
{
    void *base = kept[i].base;
    *taken = kept[i].capacity;
    kept_bytes -= *taken;
    kept[i] = kept[--nkept];
    return base;
}

/* The smallest kept block of `capacity` to SLACK_OVER (1 + 1/SLACK_OVER) times it (the
 * lock is held; its capacity in *taken), or NULL. */
static void *take_kept(size_t capacity, size_t *taken)
{
    int64_t best = -1;
    for (int64_t i = 0; i < nkept; ++i)
        if (kept[i].capacity >= capacity && kept[i].capacity - capacity <= capacity / SLACK_OVER &&
            (best < 0 || kept[i].capacity < kept[best].capacity))
            best = i;
    return best < 0 ? NULL : take_at(best, taken);
}

/* The kept mapped block of capacity nearest `capacity` (a mapped size; the lock is
 * held; its capacity in *taken), or NULL. */
static void *take_nearest_mapped(size_t capacity, size_t *taken)
{
    int64_t best = -1;
    size_t best_gap = 0;
    for (int64_t i = 0; i < nkept; ++i) {
        if (HEADER_BYTES + kept[i].capacity < MAP_BYTES)
            continue;
        size_t gap = kept[i].capacity > capacity ? kept[i].capacity - capacity : capacity - kept[i].capacity;
        if (best < 0 || gap < best_gap) {
            best = i;
            best_gap = gap;
        }
    }
    return best < 0 ? NULL : take_at(best, taken);
}

/* Release kept blocks, oldest first, until `capacity` more fits under the mark. */
static void make_room(size_t capacity)
{
    size_t mark = high_bytes > in_use_bytes + capacity ? high_bytes : in_use_bytes + capacity;
    while (nkept > 0 && in_use_bytes + kept_bytes + capacity > mark) {
        int64_t oldest = 0;
        for (int64_t i = 1; i < nkept; ++i)
            if (kept[i].serial < kept[oldest].serial)
                oldest = i;
        release_kept(oldest);
    }
}

static void *allocate(size_t size, int zeroed)
{
    size_t capacity = capacity_for(size);
    if (capacity < LARGE_BYTES) {
        void *base = block_new(HEADER_BYTES + capacity, zeroed);
        if (base == NULL)
            return NULL;
        *(size_t *)base = capacity;
        return data_of(base);
    }
    void *base = NULL, *remap = NULL;
    size_t remap_capacity = 0;
    pthread_mutex_lock(&lock);
    if (users > 0) {
        base = take_kept(capacity, &capacity);
        if (base == NULL && HEADER_BYTES + capacity >= MAP_BYTES)
            remap = take_nearest_mapped(capacity, &remap_capacity);
        if (base == NULL)
            make_room(capacity);
    }
    in_use_bytes += capacity;
    if (in_use_bytes > high_bytes)
        high_bytes = in_use_bytes;
    if (base != NULL)
        ++reused_count;
    else {
        ++fresh_count;
        fresh_bytes += (int64_t)(remap != NULL && remap_capacity < capacity ? capacity - remap_capacity
                                 : remap != NULL ? 0 : capacity);
    }
    pthread_mutex_unlock(&lock);
    if (base != NULL) {
        if (zeroed)
            memset(data_of(base), 0, capacity);
    } else if (remap != NULL) {
        base = block_resize(remap, HEADER_BYTES + remap_capacity, HEADER_BYTES + capacity);
        if (base == NULL)
            block_free(remap, HEADER_BYTES + remap_capacity);
        else if (zeroed) /* the pages it grew by are new, hence zero */
            memset(data_of(base), 0, remap_capacity < capacity ? remap_capacity : capacity);
    }
    if (base == NULL)
        base = block_new(HEADER_BYTES + capacity, zeroed);
    if (base == NULL) {
        pthread_mutex_lock(&lock);
        in_use_bytes -= capacity;
        pthread_mutex_unlock(&lock);
        return NULL;
    }
    *(size_t *)base = capacity;
    return data_of(base);
}

static void release(void *data)
{
    if (data == NULL)
        return;
    void *base = base_of(data);
    size_t capacity = *(size_t *)base;
    if (capacity >= LARGE_BYTES) {
        pthread_mutex_lock(&lock);
        in_use_bytes -= capacity;
        if (users > 0 && nkept < MAX_KEPT) {
            kept[nkept].capacity = capacity;
            kept[nkept].serial = next_serial++;
            kept[nkept].base = base;
            ++nkept;
            kept_bytes += capacity;
            base = NULL;
        }
        pthread_mutex_unlock(&lock);
    }
    if (base != NULL)
        block_free(base, HEADER_BYTES + capacity);
}

static void *handler_malloc(void *ctx, size_t size)
{
    (void)ctx;
    return allocate(size, 0);
}

static void *handler_calloc(void *ctx, size_t nelem, size_t elsize)
{
    (void)ctx;
    if (elsize != 0 && nelem > (SIZE_MAX - HEADER_BYTES - CLASS_BYTES) / elsize)
        return NULL;
    return allocate(nelem * elsize, 1);
}

static void *handler_realloc(void *ctx, void *data, size_t new_size)
{
    (void)ctx;
    if (data == NULL)
        return allocate(new_size, 0);
    size_t capacity = *(size_t *)base_of(data);
    if (capacity_for(new_size) == capacity)
        return data;
    void *moved = allocate(new_size, 0);
    if (moved == NULL)
        return NULL; /* realloc's contract: the old block stays valid */
    memcpy(moved, data, capacity < new_size ? capacity : new_size);
    release(data);
    return moved;
}

static void handler_free(void *ctx, void *data, size_t size)
{
    (void)ctx;
    (void)size; /* the header's capacity is authoritative */
    release(data);
}

GS_EXPORT gs_data_handler gs_array_cache_handler = {
    "geoidspline_array_cache", 1,
    {NULL, handler_malloc, handler_calloc, handler_realloc, handler_free},
};

/* Opens the cache for one more user (the first resets the high mark). */
GS_EXPORT void gs_array_cache_open(void)
{
    pthread_mutex_lock(&lock);
    if (users++ == 0) {
        high_bytes = in_use_bytes;
        reused_count = fresh_count = fresh_bytes = 0;
    }
    pthread_mutex_unlock(&lock);
}

/* Closes it for one user; the last releases every kept block. */
GS_EXPORT void gs_array_cache_close(void)
{
    pthread_mutex_lock(&lock);
    if (users > 0 && --users == 0)
        while (nkept > 0)
            release_kept(nkept - 1);
    pthread_mutex_unlock(&lock);
}

/* Counters since the cache opened: {reused (a kept block whole), fresh (new or remapped), in use bytes, kept bytes, high bytes, fresh bytes}. */
GS_EXPORT void gs_array_cache_counts(int64_t *out)
{
    pthread_mutex_lock(&lock);
    out[0] = reused_count;
    out[1] = fresh_count;
    out[2] = (int64_t)in_use_bytes;
    out[3] = (int64_t)kept_bytes;
    out[4] = (int64_t)high_bytes;
    out[5] = fresh_bytes;
    pthread_mutex_unlock(&lock);
}
